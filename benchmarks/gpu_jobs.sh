#!/usr/bin/env bash
# Run several benchmark/experiment jobs at once, one per GPU, on a multi-GPU machine (the device tool's
# nvidia-h200-x4: four GPUs for the price of one call), and pack what they write into one archive.
#
#   bash benchmarks/gpu_jobs.sh OUT LIMIT_S "JOB 0" "JOB 1" ...
#
# JOB i runs on GPU i as `JOB i` in a shell (e.g. "python -m benchmarks.learning --tasks ant --out @"),
# or on the GPUs it names first ("0,1: cdjax sweep ..." runs on GPUs 0 and 1, sharding its runs over both),
# with every "@" replaced by its own output folder job<i> (under a scratch folder); it is killed after
# LIMIT_S seconds. Each job's output goes to job<i>/log.txt. At the end OUT/jobs.tar.gz holds every job
# folder but checkpoints (one file: the device tool brings back at most 8), and the last lines of each log
# are printed.
set -u
out=$1; limit=$2; shift 2
work=$(mktemp -d)
export PYTHONUNBUFFERED=1
mkdir -p "$out"
nvidia-smi -L || true
i=0
for job in "$@"; do
  dir="$work/job$i"; mkdir -p "$dir"
  gpus=$i
  if [[ $job =~ ^([0-9,]+):\ (.*)$ ]]; then gpus=${BASH_REMATCH[1]}; job=${BASH_REMATCH[2]}; fi
  cmd=${job//@/$dir}
  echo "job$i (GPU $gpus): $cmd" | tee "$dir/log.txt"
  ( CUDA_VISIBLE_DEVICES=$gpus timeout -k 10 "$limit" bash -c "$cmd" >> "$dir/log.txt" 2>&1;
    echo "exit status $?" >> "$dir/log.txt" ) &
  i=$((i + 1))
done
wait
tar -czf "$out/jobs.tar.gz" --exclude=checkpoints -C "$work" $(cd "$work" && ls -d job*)  # no checkpoints
for d in "$work"/job*/; do echo "== $d"; grep -v '^task=' "$d/log.txt" | tail -n 6; done
