#!/usr/bin/env bash
# The second parity pass: three lanes, one learner process each at a time (three processes share the GPU, so the
# rows measure returns at equal env steps, not speed). Lane a: cdjax's 5 vmapped seeds per task, one task after
# another; lane b and lane c: Brax's seeds one after another. Every process is
# `python -m benchmarks.brax_sac --tasks T --frameworks cdjax|brax ...` at its task's SacTask (1M env steps).
# The whole pass stops after LIMIT seconds (default 1400); a later loan reruns what did not finish.
#   setsid bash benchmarks/results/2026-11-29-h200-sac-parity/run2.sh OUT "a-tasks" "b-task:seeds" "c-task:seeds" [LIMIT]
set -u
out=${1:?output directory}
a_tasks=${2:-}
b_spec=${3:-}
c_spec=${4:-}
limit=${5:-1400}
mkdir -p "$out"
export XLA_PYTHON_CLIENT_PREALLOCATE=false
stamp() { echo "$1 $(date -u +%T)" >> "$out/progress"; }
cdjax_lane() {
  for task in $a_tasks; do
    stamp "start $task-cdjax"
    python -m benchmarks.brax_sac --tasks "$task" --frameworks cdjax --seeds 5 --out "$out/$task-cdjax" \
      > "$out/$task-cdjax.log" 2>&1
    stamp "end $task-cdjax rc=$?"
  done
}
brax_lane() {  # spec: "task:0 1 2,task2:3 4"
  local IFS=,
  for part in $1; do
    local task=${part%%:*} seeds=${part#*:}
    IFS=' '
    for seed in $seeds; do
      stamp "start $task-brax-$seed"
      python -m benchmarks.brax_sac --tasks "$task" --frameworks brax --seeds 1 --first-seed "$seed" \
        --out "$out/$task-brax-$seed" > "$out/$task-brax-$seed.log" 2>&1
      stamp "end $task-brax-$seed rc=$?"
    done
    IFS=,
  done
}
stamp "pass start (limit ${limit}s)"
lanes=()
if [ -n "$a_tasks" ]; then cdjax_lane & lanes+=($!); fi
if [ -n "$b_spec" ]; then brax_lane "$b_spec" & lanes+=($!); fi
if [ -n "$c_spec" ]; then brax_lane "$c_spec" & lanes+=($!); fi
( sleep "$limit"; stamp "time limit"; pkill -TERM -f "[b]enchmarks.brax_sac" ) &
killer=$!
wait "${lanes[@]}"
kill "$killer" 2>/dev/null
stamp "pass done"
