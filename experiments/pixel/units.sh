#!/usr/bin/env bash
# Issue 22's GPU work in units, each inside one lease (a one-GPU machine, held at most 30 minutes; a command runs at
# most 10): started once as its own process session (setsid: it outlives the call, not the machine), then polled.
#
#   bash experiments/pixel/units.sh UNIT [WAIT_S]
#   bash experiments/pixel/units.sh --print-command UNIT   # the unit's command line, nothing started or written
#
# UNIT is one of
#   roofline       python -m experiments.pixel.roofline on halfcheetah's preset (30 runs, the real task's data):
#                  every compute_dtype/conv_impl variant, with a profile of each (roofline.json, .md, profile/)
#   precision      a reference against a faster arrangement at equal updates: halfcheetah's preset arms (ltq, ltq-cd
#                  with cc_policy 0 and 1), 10 seeds, PREC_UPDATES updates (default 300) each, once as the presets
#                  run (with REF_SET's switches, default none; until 2026-11-25, 28bb851, the presets ran
#                  float32/grouped) and once with PIXEL_SET (default "--compute-dtype bfloat16 --conv-impl auto"),
#                  then experiments.pixel.precision: held-out ELBO, log-likelihoods and imitation error per seed
#                  (precision.md); each sweep stops by half the unit's time limit. Its two runs:
#                  data/precision-h200/ and data/precision-grad-h200/ (RESULTS.md)
#   lr-check       the learning-rate check: the ltq arm on halfcheetah, 5 seeds, a vmapped grid of the model's rate
#                  (--lr) x the policy's (--lr-policy; 0 = the model's), LR_UPDATES updates (default 500) or the
#                  time limit; PIXEL_SET (e.g. "--compute-dtype bfloat16 --conv-impl per-run") picks the arrangement
#                  the roofline found fastest; no evaluation (the held-out ELBO, imitation and likelihood decide)
#   core           the update's speed with core_impl flax (the model of before) and fused (the filter's and prior's
#                  steps with fewer products: PixelConfig.core_impl), halfcheetah's ltq-cd at the preset's sizes
#                  (bfloat16/per-run), 10 runs as a TASK-ARM unit runs them, SyntheticWorld's frames, one roofline
#                  process each (flax.json/.md, fused.json/.md); about 3 minutes: whether the presets should run
#                  fused (they do; the kernel counts of data/core-h200/ came from a removed HLO reader)
#   grad-dtype     the update's speed with output_grad float32 (the model of before) and compute (the output layers'
#                  gradients as bfloat16 products: PixelConfig.output_grad), halfcheetah's ltq-cd at the preset's
#                  sizes (bfloat16/per-run, core fused), 30 runs, SyntheticWorld's frames, one roofline process each
#                  (grad-float32.json/.md, grad-bfloat16.json/.md; its run: data/grad-dtype-h200/)
#   profile        where the presets' update spends its time now: the roofline of halfcheetah's ltq-cd as the presets
#                  run it (bfloat16/per-run, core fused, output_grad compute), 30 runs, SyntheticWorld's frames, with
#                  a profile (presets.json/.md, profile/); then the same with XLA_FLAGS
#                  --xla_gpu_enable_dynamic_slice_fusion=true (slice-fusion.json/.md; skipped where the image's XLA
#                  refuses it at start-up): per-run convolutions read each run's operands as slices of the stacked runs, which
#                  XLA copies out unless it fuses the slice into the cuDNN call (about 4 minutes)
#   sweep-speed    issue 22's before and after in one command: halfcheetah's preset sweep (30 runs: ltq and ltq-cd
#                  with cc_policy 0 and 1, 10 seeds) for SPEED_UPDATES updates (default 200), once as the model
#                  of before (--compute-dtype float32 --conv-impl grouped --core-impl flax --lr-policy 0) and once
#                  as the presets run it; each sweep's "Trained in" line gives its frames/s (about 8 minutes)
#   sweep-long     the presets' sweep as the 41,440 frames/s before it ran (the fourth pass: halfcheetah's 30 runs,
#                  1,400 updates in chunks of 200, one H200): LONG_UPDATES (default 1400) updates, stopped by
#                  LONG_LIMIT_S (default 480 s, compile included), no evaluation; its "Trained in" line gives the
#                  frames/s and the seconds between chunks, over a length where one round's fixed costs (the first
#                  chunk, the last checkpoint's write) weigh as they did then (about 5-6 minutes)
#   devices        (a multi-GPU machine, issue 25) the pixel sweep's frames/s on 1, 2 and 4 of its GPUs in one
#                  process (experiments.pixel.speed --devices; DEVICE_COUNTS, default "1 2 4"), 32 runs of halfcheetah
#                  (its run: experiments/pixel/data/devices-h100x4/)
#   TASK-ARM       the experiment at the presets' length: TASK halfcheetah, reacher or pusher, ARM ltq, ltq-cd
#                  (alpha 100, cc_policy 0 and 1: 20 runs), ltq-cd0 or ltq-cd1 (ltq-cd with cc_policy 0 or 1
#                  alone: 10 runs, `--arms ltq-cd --cc-policy N`; not the CLI's arm ltq-cdN, which is ltq-cd with
#                  horizon N), 10 seeds, 10,000 updates or what fits before the time limit (stated in the run's
#                  log), then evaluated from pixels, plotted and its strips drawn. Each unit's tarball unpacks to
#                  its own directory (TASK-ARM/pixel); `python -m experiments.pixel.report DIR` over a directory of
#                  them puts a task's units side by side and compares them at the update all of them reached.
#
# The presets' length (issue 22): the nine units TASK-ltq, TASK-ltq-cd0 and TASK-ltq-cd1 for the three tasks, one
# per lease, all run (their times per unit and frames/s: RESULTS.md, "Fifth pass"; halfcheetah's cd units before
# the encoder-balance fix: data/presets-length-collapsed/). One unit fits a one-GPU machine held 30 minutes, or one
# and sweep-speed, or a second unit with LIMIT_S/END_S cut to the machine's time left. A unit
# whose runs are slower than an estimate says in its log where --time-limit stopped it; each unit's "Trained in"
# line gives its real rate. Fewer runs may not be proportionally faster (the update is bound by kernel launches).
# The experts are the kept ones (experiments/pixel/data/three-tasks-x2/TASK/expert.msgpack). The first call starts
# the unit in runs/pixel-units/UNIT/ and waits; every call waits up to WAIT_S seconds (default 560) for it to end,
# then says "RUNNING: call again" (at once: the machine goes back 30 s after a call) or "DONE" after packing what to
# keep into $OUT (default runs/pixel-units-out): UNIT.tar.gz (run directories without checkpoints, metrics thinned
# by experiments.thin_logs) and UNIT.log. Sweeps stop by --time-limit (LIMIT_S, default 1260 s from the unit's
# start, compile included); evaluation, plots and strips take about 6 more minutes (a TASK-ARM unit's evaluation
# gets up to EVAL_S, default 300 s, less where the strips would then end past END_S, default 1680 s from the start).
# The GPU image has no `cdjax` console script: everything runs as python -m.
set -u
print_only=0
if [ "${1:-}" = "--print-command" ]; then print_only=1; shift; fi
unit=${1:?usage: units.sh [--print-command] UNIT [WAIT_S]}; wait_s=${2:-560}
work=runs/pixel-units/$unit
out=${OUT:-runs/pixel-units-out}
limit=${LIMIT_S:-1260}
end=${END_S:-1680}
eval_max=${EVAL_S:-300}
experts=experiments/pixel/data/three-tasks-x2
t0=$(date +%s)
export PYTHONUNBUFFERED=1

command_of() {  # UNIT -> the unit's commands (one bash line)
  case "$1" in
    roofline)
      echo "python -m experiments.pixel.roofline --env halfcheetah --runs 30 --profile $work/profile" \
        "--out $work/roofline.json" ;;
    core)
      local rf="python -m experiments.pixel.roofline --env halfcheetah --runs 10 --variants bfloat16/per-run --synthetic"
      local line="" impl
      for impl in flax fused; do
        line+="$rf --set core_impl=$impl --out $work/$impl.json > $work/$impl.log 2>&1;"
      done
      echo "$line cat $work/flax.md $work/fused.md" ;;
    grad-dtype)
      local rf="python -m experiments.pixel.roofline --env halfcheetah --runs 30 --variants bfloat16/per-run --synthetic"
      rf="$rf --set core_impl=fused output_grad"
      echo "$rf=float32 --out $work/grad-float32.json > $work/grad-float32.log 2>&1;" \
        "$rf=compute --out $work/grad-bfloat16.json > $work/grad-bfloat16.log 2>&1;" \
        "cat $work/grad-float32.md $work/grad-bfloat16.md" ;;
    profile)
      local rf="python -m experiments.pixel.roofline --env halfcheetah --runs 30 --variants bfloat16/per-run --synthetic"
      local flag=xla_gpu_enable_dynamic_slice_fusion=true
      echo "$rf --profile $work/profile --out $work/presets.json > $work/presets.log 2>&1;" \
        "XLA_FLAGS=--$flag $rf --out $work/slice-fusion.json > $work/slice-fusion.log 2>&1" \
        "|| echo 'this XLA refuses ${flag%%=*} (slice-fusion.log)';" \
        "cat $work/presets.md $work/slice-fusion.md; head -n 40 $work/profile/*.md" ;;
    sweep-speed)
      local sweep="python -m cdjax.cli sweep --setting pixel --preset pixel-halfcheetah"
      sweep="$sweep --expert $experts/halfcheetah/expert.msgpack --steps $(( ${SPEED_UPDATES:-200} * 800 ))"
      sweep="$sweep --chunk-updates 100 --no-progress --no-final-eval --time-limit 300"
      echo "timeout -s INT -k 60 420 $sweep --compute-dtype float32 --conv-impl grouped --core-impl flax --lr-policy 0" \
        "--out $work/before > $work/before.log 2>&1; timeout -s INT -k 60 420 $sweep --out $work/presets" \
        "> $work/presets.log 2>&1; grep -H -E 'Arms|Trained in' $work/before.log $work/presets.log" ;;
    sweep-long)
      local sweep="python -m cdjax.cli sweep --setting pixel --preset pixel-halfcheetah"
      sweep="$sweep --expert $experts/halfcheetah/expert.msgpack --steps $(( ${LONG_UPDATES:-1400} * 800 ))"
      echo "timeout -s INT -k 60 $(( ${LONG_LIMIT_S:-480} + 120 )) $sweep --no-progress --no-final-eval" \
        "--time-limit ${LONG_LIMIT_S:-480} --out $work/presets > $work/presets.log 2>&1;" \
        "grep -H -E 'Arms|Trained in|Stopped' $work/presets.log" ;;
    devices)
      echo "python -m experiments.pixel.speed --env halfcheetah --runs 32 --devices ${DEVICE_COUNTS:-1 2 4}" \
        "--out $work/devices.json" ;;
    precision)
      local fast=${PIXEL_SET:---compute-dtype bfloat16 --conv-impl auto}
      local sweep="python -m cdjax.cli sweep --setting pixel --preset pixel-halfcheetah"
      sweep="$sweep --expert $experts/halfcheetah/expert.msgpack --seeds 10 --steps $(( ${PREC_UPDATES:-300} * 800 ))"
      sweep="$sweep --no-progress --no-final-eval --time-limit $(( limit / 2 ))"
      echo "timeout -s INT -k 60 $(( limit / 2 + 120 )) $sweep ${REF_SET:-} --out $work/reference;" \
        "timeout -s INT -k 60 $(( limit / 2 + 120 )) $sweep $fast --out $work/candidate;" \
        "python -m experiments.pixel.precision $work/reference $work/candidate --labels '${REF_SET:-presets}' '$fast'" \
        "--out $work/precision.md" ;;
    lr-check)
      echo "timeout -s INT -k 60 $(( limit + 300 )) python -m cdjax.cli sweep --setting pixel" \
        "--preset pixel-halfcheetah --expert $experts/halfcheetah/expert.msgpack --arms ltq --seeds 5" \
        "--lr ${LRS:-3e-5 1e-4 3e-4 1e-3} --lr-policy ${LR_POLICIES:-0 1e-3} --steps $(( ${LR_UPDATES:-500} * 800 ))" \
        "${PIXEL_SET:-} --no-progress --no-final-eval --time-limit $limit --out $work/lr; python -m cdjax.cli plot $work/lr" ;;
    halfcheetah-*|reacher-*|pusher-*)
      local task=${1%%-*} arm=${1#*-} arms
      case "$arm" in
        ltq|ltq-cd) arms="--arms $arm" ;;
        ltq-cd0|ltq-cd1) arms="--arms ltq-cd --cc-policy ${arm#ltq-cd}" ;;
        *) echo "unknown arm $arm of unit $1: ltq, ltq-cd, ltq-cd0 or ltq-cd1" >&2; return 1 ;;
      esac
      # The evaluation gets up to EVAL_S (default 300) s, fewer where that would leave less than the strips' 160 s
      # and 20 s for the plot before END_S (default 1680 s, 28 minutes, from the unit's start: the lease's 30 less
      # the machine's start and the packing), but at least 120. 200 s was tight for pusher: its evaluation took over
      # 120 s for 20 runs (second pass) and 105.9 s of evaluating alone for 30 (fourth pass; restoring the sweep,
      # which renders its data and compiles init again, comes on top), and no bfloat16 evaluation has been timed.
      local eval_s="\$(( $end - \$(date +%s) + \$(cat $work/started) - 180 ))"
      echo "timeout -s INT -k 60 $(( limit + 300 )) python -m cdjax.cli sweep --setting pixel --preset pixel-$task" \
        "--expert $experts/$task/expert.msgpack $arms ${PIXEL_SET:-} --no-progress --no-final-eval" \
        "--time-limit $limit --out $work/pixel; s=$eval_s;" \
        "timeout -k 30 \$(( s > $eval_max ? $eval_max : s < 120 ? 120 : s )) python -m cdjax.cli eval $work/pixel" \
        "--episodes 4; python -m cdjax.cli plot $work/pixel; timeout -k 10 150 python -m experiments.pixel.report" \
        "--strips $work/pixel $work/strips" ;;
    *) echo "unknown unit $1: roofline, core, grad-dtype, profile, sweep-speed, sweep-long, precision, devices, lr-check or TASK-ARM (halfcheetah, reacher, pusher x ltq," \
         "ltq-cd, ltq-cd0, ltq-cd1)" >&2
       return 1 ;;
  esac
}

cmd=$(command_of "$unit") || exit 2
if [ "$print_only" = 1 ]; then echo "$cmd"; exit 0; fi
mkdir -p "$work" "$out"
. "$(dirname "$0")/../lease.sh"
ensure_wheels || exit 1
unit_run "$work" "$cmd" "$wait_s" "$t0" "bash experiments/pixel/units.sh $unit" || exit 0
thin=runs/pixel-units-thin
rm -rf "${thin:?}/$unit" && python -m experiments.thin_logs "$work" "$thin/$unit" >/dev/null
mkdir -p "$thin/$unit"
for f in command before.log presets.log presets.json presets.md slice-fusion.json slice-fusion.md slice-fusion.log grad-float32.json grad-float32.md grad-float32.log grad-bfloat16.json grad-bfloat16.md grad-bfloat16.log roofline.json roofline.md profile devices.json strips precision.md precision.json flax.json flax.md fused.json fused.md loops-flax.log loops-fused.log; do [ -e "$work/$f" ] && cp -r "$work/$f" "$thin/$unit/"; done
tar -czf "$out/$unit.tar.gz" -C "$thin" "$unit"
cp "$work/unit.log" "$out/$unit.log"
echo "DONE: unit $unit, exit status $(cat "$work/exit_code"), $(( $(date +%s) - $(cat "$work/started") )) s since it started"
ls -l "$out"
grep -v -i -E "warn|^\s*$" "$work/unit.log" | tail -n 20
