#!/usr/bin/env bash
# The parity runs of cdjax's off-policy setting (model-free arm) against Brax's SAC: every task at its SacTask
# (benchmarks/brax_sac.py: 128 envs, 8 gradient steps per batched env step, 1M env steps, 11 evaluations of 128
# episodes), 5 seeds each side. Processes share the GPU: per task, cdjax's 5 vmapped seeds in one process beside
# five Brax processes of one seed each, two tasks at a time; so this measures returns at equal env steps, not speed
# (the speed case runs alone: `python -m benchmarks.brax_sac --speed`).
#   setsid bash benchmarks/results/2026-11-29-h200-sac-parity/run.sh OUT
set -u
out=${1:?output directory}
mkdir -p "$out"
export XLA_PYTHON_CLIENT_PREALLOCATE=false
lane() {
  for task in "$@"; do
    python -m benchmarks.brax_sac --tasks "$task" --frameworks cdjax --seeds 5 --out "$out/$task-cdjax" \
      > "$out/$task-cdjax.log" 2>&1 &
    for seed in 0 1 2 3 4; do
      python -m benchmarks.brax_sac --tasks "$task" --frameworks brax --seeds 1 --first-seed "$seed" \
        --out "$out/$task-brax-$seed" > "$out/$task-brax-$seed.log" 2>&1 &
    done
    wait
    echo "$task done $(date -u +%T)" >> "$out/progress"
  done
}
echo "start $(date -u +%T)" > "$out/progress"
lane ant hopper &
lane halfcheetah humanoid &
wait
echo "all done $(date -u +%T)" >> "$out/progress"
