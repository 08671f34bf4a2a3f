#!/usr/bin/env bash
# Issue 22's GPU work in units, each inside one lease (a one-GPU machine, held at most 30 minutes; a command runs at
# most 10): started once as its own process session (setsid: it outlives the call, not the machine), then polled.
#
#   bash experiments/pixel/units.sh UNIT [WAIT_S]
#
# UNIT is one of
#   roofline       python -m experiments.pixel.roofline on halfcheetah's preset (30 runs, the real task's data):
#                  every compute_dtype/conv_impl variant, with a profile of each (roofline.json, .md, profile/)
#   precision      float32 against a faster arrangement at equal updates: halfcheetah's preset arms (ltq, ltq-cd with
#                  cc_policy 0 and 1), 10 seeds, PREC_UPDATES updates (default 300) each, once in float32/grouped and
#                  once with PIXEL_SET (default "--compute-dtype bfloat16 --conv-impl auto"), then
#                  experiments.pixel.precision: held-out ELBO, log-likelihoods and imitation error per seed
#                  (precision.md); each sweep stops by half the unit's time limit
#   lr-check       the learning-rate check: the ltq arm on halfcheetah, 5 seeds, a vmapped grid of the model's rate
#                  (--lr) x the policy's (--lr-policy; 0 = the model's), LR_UPDATES updates (default 500) or the
#                  time limit; PIXEL_SET (e.g. "--compute-dtype bfloat16 --conv-impl per-run") picks the arrangement
#                  the roofline found fastest; no evaluation (the held-out ELBO, imitation and likelihood decide)
#   devices        (a multi-GPU machine, issue 25) the pixel sweep's frames/s on 1, 2 and 4 of its GPUs in one
#                  process (experiments.pixel.speed --devices; DEVICE_COUNTS, default "1 2 4"), 32 runs of halfcheetah
#   TASK-ARM       the experiment at the presets' length: TASK halfcheetah, reacher or pusher, ARM ltq or ltq-cd
#                  (ltq-cd: alpha 100, cc_policy 0 and 1), 10 seeds, 10,000 updates or what fits before the time
#                  limit (stated in the run's log), then evaluated from pixels, plotted and its strips drawn
# The experts are the kept ones (experiments/pixel/data/three-tasks-x2/TASK/expert.msgpack). The first call starts
# the unit in runs/pixel-units/UNIT/ and waits; every call waits up to WAIT_S seconds (default 560) for it to end,
# then says "RUNNING: call again" (at once: the machine goes back 30 s after a call) or "DONE" after packing what to
# keep into $OUT (default runs/pixel-units-out): UNIT.tar.gz (run directories without checkpoints, metrics thinned
# by experiments.thin_logs) and UNIT.log. Sweeps stop by --time-limit (LIMIT_S, default 1260 s from the unit's
# start, compile included); evaluation, plots and strips take about 6 more minutes.
# The GPU image has no `cdjax` console script: everything runs as python -m.
set -u
unit=$1; wait_s=${2:-560}
work=runs/pixel-units/$unit
out=${OUT:-runs/pixel-units-out}
limit=${LIMIT_S:-1260}
experts=experiments/pixel/data/three-tasks-x2
t0=$(date +%s)
export PYTHONUNBUFFERED=1

command_of() {  # UNIT -> the unit's commands (one bash line)
  case "$1" in
    roofline)
      echo "python -m experiments.pixel.roofline --env halfcheetah --runs 30 --profile $work/profile" \
        "--out $work/roofline.json" ;;
    devices)
      echo "python -m experiments.pixel.speed --env halfcheetah --runs 32 --devices ${DEVICE_COUNTS:-1 2 4}" \
        "--out $work/devices.json" ;;
    precision)
      local fast=${PIXEL_SET:---compute-dtype bfloat16 --conv-impl auto}
      local sweep="python -m cdjax.cli sweep --setting pixel --preset pixel-halfcheetah"
      sweep="$sweep --expert $experts/halfcheetah/expert.msgpack --seeds 10 --steps $(( ${PREC_UPDATES:-300} * 800 ))"
      sweep="$sweep --no-progress --no-final-eval --time-limit $(( limit / 2 ))"
      echo "timeout -s INT -k 60 $(( limit / 2 + 120 )) $sweep --out $work/float32;" \
        "timeout -s INT -k 60 $(( limit / 2 + 120 )) $sweep $fast --out $work/candidate;" \
        "python -m experiments.pixel.precision $work/float32 $work/candidate --labels float32 '$fast'" \
        "--out $work/precision.md" ;;
    lr-check)
      echo "timeout -s INT -k 60 $(( limit + 300 )) python -m cdjax.cli sweep --setting pixel" \
        "--preset pixel-halfcheetah --expert $experts/halfcheetah/expert.msgpack --arms ltq --seeds 5" \
        "--lr ${LRS:-3e-5 1e-4 3e-4 1e-3} --lr-policy ${LR_POLICIES:-0 1e-3} --steps $(( ${LR_UPDATES:-500} * 800 ))" \
        "${PIXEL_SET:-} --no-progress --no-final-eval --time-limit $limit --out $work/lr; python -m cdjax.cli plot $work/lr" ;;
    halfcheetah-ltq|halfcheetah-ltq-cd|reacher-ltq|reacher-ltq-cd|pusher-ltq|pusher-ltq-cd)
      local task=${1%%-*} arm=${1#*-}
      echo "timeout -s INT -k 60 $(( limit + 300 )) python -m cdjax.cli sweep --setting pixel --preset pixel-$task" \
        "--expert $experts/$task/expert.msgpack --arms $arm ${PIXEL_SET:-} --no-progress --no-final-eval" \
        "--time-limit $limit --out $work/pixel; timeout -k 30 200 python -m cdjax.cli eval $work/pixel --episodes 4;" \
        "python -m cdjax.cli plot $work/pixel; timeout -k 10 150 python -m experiments.pixel.report --strips" \
        "$work/pixel $work/strips" ;;
    *) echo "unknown unit $1: roofline, precision, devices, lr-check or TASK-ARM (halfcheetah, reacher, pusher x ltq, ltq-cd)" >&2
       return 1 ;;
  esac
}

cmd=$(command_of "$unit") || exit 2
mkdir -p "$work" "$out"
. "$(dirname "$0")/../lease.sh"
ensure_wheels || exit 1
unit_run "$work" "$cmd" "$wait_s" "$t0" "bash experiments/pixel/units.sh $unit" || exit 0
thin=runs/pixel-units-thin
rm -rf "${thin:?}/$unit" && python -m experiments.thin_logs "$work" "$thin/$unit" >/dev/null
mkdir -p "$thin/$unit"
for f in command roofline.json roofline.md profile devices.json strips precision.md precision.json; do [ -e "$work/$f" ] && cp -r "$work/$f" "$thin/$unit/"; done
tar -czf "$out/$unit.tar.gz" -C "$thin" "$unit"
cp "$work/unit.log" "$out/$unit.log"
echo "DONE: unit $unit, exit status $(cat "$work/exit_code"), $(( $(date +%s) - $(cat "$work/started") )) s since it started"
ls -l "$out"
grep -v -i -E "warn|^\s*$" "$work/unit.log" | tail -n 20
