#!/usr/bin/env bash
# Train several tasks at once, one per GPU, each stopped after a time limit; pack the logs.
#
#   bash experiments/paper_obs_space/device.sh OUT SECONDS TASK [TASK ...] [-- extra train options]
#
# Task i runs on GPU i (CUDA_VISIBLE_DEVICES=i) as `python -m experiments.paper_obs_space train --task TASK
# --out runs/paper/TASK`. A run that is still going after SECONDS gets SIGINT: it finishes the chunk in
# flight, saves a checkpoint and its logs, and the report compares the arms at the env steps all reached.
# OUT/TASK.tar.gz holds the run directory without checkpoints and TensorBoard files; OUT/TASK.log the output.
set -u
out=$1; limit=$2; shift 2
tasks=(); while [ $# -gt 0 ] && [ "$1" != "--" ]; do tasks+=("$1"); shift; done
[ "${1:-}" = "--" ] && shift
mkdir -p "$out" runs/paper
pids=()
for i in "${!tasks[@]}"; do
  t=${tasks[$i]}
  CUDA_VISIBLE_DEVICES=$i timeout -s INT -k 60 "$limit" \
    python -m experiments.paper_obs_space train --task "$t" --out "runs/paper/$t" "$@" \
    >"$out/$t.log" 2>&1 &
  pids+=($!)
done
for p in "${pids[@]}"; do wait "$p"; done
for t in "${tasks[@]}"; do
  tar -czf "$out/$t.tar.gz" --exclude=checkpoints --exclude=tb -C runs/paper "$t"
  echo "== $t"; tail -n 6 "$out/$t.log"
done
