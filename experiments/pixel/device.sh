#!/usr/bin/env bash
# The pixel setting on a GPU machine: experts, expert data, Learning to Query vs Learning to Query + consistency.
#
#   bash experiments/pixel/device.sh WORK RESULTS SECONDS [TASK ...]   # tasks: halfcheetah reacher pusher (default all)
#
# WORK holds the runs (checkpoints included; e.g. runs/pixel, kept between calls on the same machine), RESULTS
# receives what to keep (each task's run directories without checkpoints, their metrics thinned by
# experiments.thin_logs, the expert, cost and strips; the logs, report.md and figures/). Everything stops before
# SECONDS (wall clock of this call) and can be continued: call it again with the same WORK and it resumes where it
# stopped (experts already exported are kept; the pixel sweeps run with --resume; the JAX compilation cache in
# ~/.cache/cdjax/jax is reused). A call can also outlive a 10-minute command: start it with setsid and collect
# RESULTS later (every resume re-renders the data and reloads the programs: one long call wastes nothing).
# The tasks run side by side (task i on GPU i mod the number of GPUs, sharing its memory where they share a GPU);
# SEQUENTIAL=1 runs them one after another, each with its share of the time.
# Per task, in WORK/TASK/:
#   1. expert-run/   cdjax's model-free arm on the state (obs setting, the task's preset, 1 seed), stopped at
#                    EXPERT_SHARE of the task's time; evaluated; its policy -> expert.msgpack
#   2. cost.json     data_cost: the dataset kept on the device vs rendered on the fly (10 runs vmapped), for the
#                    tasks in COST_TASKS (default all) that have none yet, before their sweeps start; the
#                    measurements of the tasks sharing a GPU run one after another, before any of their sweeps
#   3. pixel/        cdjax sweep --setting pixel --preset pixel-TASK (ltq and ltq-cd, 10 seeds vmapped, k = 10
#                    halfcheetah, 5 reacher/pusher), stopped by its --time-limit, then (FINAL=1, the default)
#                    evaluated (the imitation policy from pixels) and plotted; FINAL=0 (a call that another will
#                    continue) trains until the end of the call instead
#   4. strips/       PNG strips of held-out sequences (real / reconstructed / open loop) of seed 0 of each
#                    hyper-parameter set, in FINAL calls (STRIPS=0: not)
# then WORK/report.md and WORK/figures/ (python -m experiments.pixel.report WORK). WORK/TASK.log holds the output.
# The GPU image has no `cdjax` console script: everything runs as python -m.
set -u
out=$1; results=$2; limit=$3; shift 3
tasks=("$@"); [ ${#tasks[@]} -eq 0 ] && tasks=(halfcheetah reacher pusher)
EXPERT_SHARE=${EXPERT_SHARE:-30}   # percent of a task's time for its expert (first call only)
EXPERT_STEPS=${EXPERT_STEPS:-20000000}  # the expert's env-step budget (the SIGINT usually comes first)
EXPERT_ARGS=${EXPERT_ARGS:-}  # more options of the expert's sweep (a CPU smoke test shrinks it)
COST_TASKS=${COST_TASKS-halfcheetah reacher pusher}  # the tasks whose data cost is measured (empty: none)
FINAL=${FINAL:-1}             # 1: evaluate, plot and draw the strips at the end of this call
PIXEL_ARGS=${PIXEL_ARGS:-}    # more options of the pixel sweep (e.g. --preset pixel-tiny --seeds 2 --steps 72)
start=$(date +%s)
mkdir -p "$out" "$results"
ngpu=$(nvidia-smi -L 2>/dev/null | wc -l); [ "$ngpu" -ge 1 ] || ngpu=1
# side by side (task i on GPU i mod ngpu; tasks sharing a GPU split its memory), unless SEQUENTIAL=1: on a
# shared GPU the compilations and host-side work of one task overlap another's kernels
parallel=1; [ "${SEQUENTIAL:-0}" = 1 ] && parallel=0
share=$(( (${#tasks[@]} + ngpu - 1) / ngpu ))
# MEM_FRACTION (each process's share of its GPU's memory) overrides 0.9 / (tasks per GPU), e.g. to leave room
if [ -n "${MEM_FRACTION:-}" ]; then export XLA_PYTHON_CLIENT_MEM_FRACTION=$MEM_FRACTION
elif [ "$share" -gt 1 ]; then export XLA_PYTHON_CLIENT_MEM_FRACTION=$(python -c "print(round(0.9 / $share, 2))"); fi

left() { echo $(( $1 - ($(date +%s) - start) )); }

carried_expert() {  # TASK: EXPERTS_FROM=DIR: DIR/TASK.msgpack is an expert of an earlier machine (carry DIR, not
  # WORK: a carried path replaces the device's copy, runs included); copied in unless the task has its expert
  if [ -n "${EXPERTS_FROM:-}" ] && [ ! -f "$out/$1/expert.msgpack" ] && [ -f "$EXPERTS_FROM/$1.msgpack" ]; then
    cp "$EXPERTS_FROM/$1.msgpack" "$out/$1/expert.msgpack"
  fi
}

run_task() {  # TASK GPU SECONDS
  local t=$1 gpu=$2 budget=$3 t0 d expert_s
  t0=$(date +%s); d="$out/$t"; mkdir -p "$d"
  carried_expert "$t"
  export CUDA_VISIBLE_DEVICES=$gpu
  task_left() { echo $(( budget - ($(date +%s) - t0) )); }
  if [ ! -f "$d/expert.msgpack" ]; then
    expert_s=$(( budget * EXPERT_SHARE / 100 ))
    local resume=(); [ -f "$d/expert-run/run.json" ] && resume=(--resume)
    if [ ${#resume[@]} -gt 0 ]; then
      timeout -s INT -k 60 $(( expert_s + 300 )) python -m cdjax.cli sweep --out "$d/expert-run" --resume \
        --no-progress --time-limit "$expert_s"
    else
      timeout -s INT -k 60 $(( expert_s + 300 )) python -m cdjax.cli sweep --setting obs --preset "$t" \
        --arms model-free --seeds 1 --steps "$EXPERT_STEPS" --no-progress --out "$d/expert-run" \
        --time-limit "$expert_s" $EXPERT_ARGS
    fi
    grep -q '"deterministic": true' "$d/expert-run/eval.jsonl" 2>/dev/null || \
      python -m cdjax.cli eval "$d/expert-run" --episodes 16
    python -m cdjax.runner.export_expert "$d/expert-run" "$d/expert.msgpack" || return 1
  fi
  [ "${EXPERTS_ONLY:-0}" = 1 ] && return 0  # EXPERTS_ONLY=1: stop after the experts (e.g. to carry them elsewhere)
  # after the sweep (FINAL=1): the evaluation and the plots (230 s; pusher's 20 runs took over 120 s to evaluate) and
  # the strips (160 s: restoring a sweep renders its data again); FINAL=0: the last chunk's checkpoint (30 s)
  local reserve=30 strips_due=0
  if [ "$FINAL" = 1 ]; then
    reserve=230; [ "${STRIPS:-1}" = 1 ] && { strips_due=1; reserve=$(( reserve + 160 )); }
  fi
  local pix_s=$(( $(task_left) - reserve ))
  if [ "$pix_s" -gt 60 ]; then  # --time-limit stops it between chunks; timeout only guards against a hang
    if [ -f "$d/pixel/run.json" ]; then
      timeout -s INT -k 60 $(( pix_s + 300 )) python -m cdjax.cli sweep --out "$d/pixel" --resume --no-progress \
        --time-limit "$pix_s"
    else
      timeout -s INT -k 60 $(( pix_s + 300 )) python -m cdjax.cli sweep --setting pixel --preset "pixel-$t" \
        --expert "$d/expert.msgpack" --no-progress --no-final-eval --out "$d/pixel" --time-limit "$pix_s" $PIXEL_ARGS
    fi
  fi
  if [ "$FINAL" = 1 ] && [ -f "$d/pixel/run.json" ]; then
    timeout -k 30 200 python -m cdjax.cli eval "$d/pixel" --episodes 4 || echo "evaluation did not finish"
    python -m cdjax.cli plot "$d/pixel" || true
    if [ "$strips_due" = 1 ] && [ "$(task_left)" -gt 100 ]; then
      timeout -k 10 150 python -m experiments.pixel.report --strips "$d/pixel" "$d/strips" || echo "no strips"
    fi
  fi
}

cost_due() {  # TASK: whether its data cost is still to be measured
  [[ " $COST_TASKS " == *" $1 "* ]] && [ ! -f "$out/$1/cost.json" ] && [ "${EXPERTS_ONLY:-0}" != 1 ]
}

measure_cost() {  # TASK GPU: the data cost, alone on its GPU (needs the expert; 10 runs, about 150 s)
  local t=$1 d="$out/$1"
  carried_expert "$t"
  [ -f "$d/expert.msgpack" ] || { echo "no expert for $t: its data cost comes after its expert"; return 0; }
  CUDA_VISIBLE_DEVICES=$2 timeout -k 20 240 python -m experiments.pixel.data_cost --env "$t" \
    --expert "$d/expert.msgpack" --runs 10 --out "$d/cost.json" || echo "data_cost did not finish"
}

for t in "${tasks[@]}"; do mkdir -p "$out/$t"; done
if [ "$parallel" = 1 ]; then
  pids=()
  for (( g = 0; g < ngpu && g < ${#tasks[@]}; g++ )); do
    (  # the tasks of GPU g: their data costs one after another, then their sweeps side by side
      for i in "${!tasks[@]}"; do
        [ $(( i % ngpu )) = "$g" ] && cost_due "${tasks[$i]}" && measure_cost "${tasks[$i]}" "$g" >>"$out/${tasks[$i]}.log" 2>&1
      done
      gp=()
      for i in "${!tasks[@]}"; do
        [ $(( i % ngpu )) = "$g" ] || continue
        run_task "${tasks[$i]}" "$g" "$(( $(left "$limit") - 30 ))" >>"$out/${tasks[$i]}.log" 2>&1 &
        gp+=($!)
      done
      for p in "${gp[@]}"; do wait "$p"; done
    ) &
    pids+=($!)
  done
  for p in "${pids[@]}"; do wait "$p"; done
else
  n=${#tasks[@]}
  for i in "${!tasks[@]}"; do
    cost_due "${tasks[$i]}" && measure_cost "${tasks[$i]}" 0 >>"$out/${tasks[$i]}.log" 2>&1
    share=$(( ($(left "$limit") - 30) / (n - i) ))
    run_task "${tasks[$i]}" 0 "$share" >>"$out/${tasks[$i]}.log" 2>&1
  done
fi
python -m experiments.pixel.report "$out" || echo "report failed"
cp -r "$out/report.md" "$out/figures" "$results/" 2>/dev/null
for t in "${tasks[@]}"; do
  cp "$out/$t.log" "$results/"
  if [ -n "$(ls -A "$out/$t" 2>/dev/null)" ]; then  # run dirs with thinned metrics (experiments.thin_logs), cost, strips, expert
    rm -rf "$out/thin/$t" && python -m experiments.thin_logs "$out/$t" "$out/thin/$t" >/dev/null; mkdir -p "$out/thin/$t"
    for f in cost.json expert.msgpack strips; do [ -e "$out/$t/$f" ] && cp -r "$out/$t/$f" "$out/thin/$t/"; done
    tar -czf "$results/$t.tar.gz" -C "$out/thin" "$t"
  fi
  echo "== $t"; tail -n 4 "$out/$t.log"
done
