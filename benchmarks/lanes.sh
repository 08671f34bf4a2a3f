#!/usr/bin/env bash
# GPU units as lanes, for learning parity (returns at equal env steps, not speed: the lanes share the GPU).
#   setsid bash benchmarks/lanes.sh OUT LANES [LIMIT] > OUT.log 2>&1 < /dev/null &
# Each line of the file LANES is one lane (blank lines and "#" comments skipped); its jobs, separated by ";;", run one
# after another, and the lanes run side by side. A job is "NAME ARGS...", run from the repository root as
#   python -m MODULE ARGS [TIME_ARG SECONDS_LEFT] --out OUT/NAME > OUT/NAME.log 2>&1   ({OUT} in ARGS: OUT)
# MODULE: benchmarks.brax_sac (the default), or benchmarks.learning with TIME_ARG=--time-limit, which then stops its
# runs at an evaluation before LIMIT and skips, when run again, the seeds whose rows are complete. A job that ends
# with status 0 and without a "time limit:" or "budget:" line in its log is marked OUT/NAME/done and skipped by a
# later run of the same file: run it again in the next loan and only what did not finish runs (an unfinished
# benchmarks.brax_sac job starts over). Everything is stopped (SIGTERM) after LIMIT seconds (default 1400), and no
# job starts after that. With more than one lane the rows' meta says that the device was shared (their times are not
# speeds); a file of one lane runs its jobs alone, one after another, and so times them.
# OUT/progress says when each job started and ended. It refuses to start when brax, MJX or cdjax cannot be imported
# (each device call is a fresh shell: export PYTHONPATH in the command that starts it).
set -u
out=$(realpath -m "${1:?output directory}")
lanes=$(realpath "${2:?lane file}")
limit=${3:-1400}
module=${MODULE:-benchmarks.brax_sac}
time_arg=${TIME_ARG:-}
cd "$(dirname "$0")/.."  # the repository root
mkdir -p "$out"
export XLA_PYTHON_CLIENT_PREALLOCATE=false
if [ "$(grep -cvE '^[[:space:]]*(#|$)' "$lanes")" -gt 1 ]; then
  export CDJAX_BENCH_SHARED_DEVICE=1  # several lanes share the device: the rows' meta says their times are not speeds
fi
start=$(date +%s)
stamp() { echo "$1 $(date -u +%T)" >> "$out/progress"; }
lane() {
  local line=$1 job name args timing rc
  while [ -n "$line" ]; do
    job=${line%%;;*}
    if [ "$job" = "$line" ]; then line=""; else line=${line#*;;}; fi
    read -r name args <<< "$job"
    args=${args//\{OUT\}/$out}  # {OUT} in a job's arguments: the output directory (e.g. --trace {OUT}/trace)
    [ -z "$name" ] && continue
    if [ -f "$out/$name/done" ]; then stamp "skip $name (done)"; continue; fi
    if [ -f "$out/.stopped" ]; then stamp "not started $name (time limit)"; continue; fi
    timing=()
    [ -n "$time_arg" ] && timing=("$time_arg" $(( limit - 30 - $(date +%s) + start )))
    stamp "start $name"
    # shellcheck disable=SC2086
    python -m "$module" $args ${timing[@]+"${timing[@]}"} --out "$out/$name" > "$out/$name.log" 2>&1
    rc=$?
    if [ $rc -eq 0 ] && ! grep -qE "^(time limit|budget):" "$out/$name.log"; then touch "$out/$name/done"; fi
    stamp "end $name rc=$rc"
  done
}
if ! python -c "import brax, mujoco.mjx, cdjax" 2> "$out/import-error"; then  # a lane of failed jobs is a lost loan
  stamp "cannot import brax, mujoco.mjx or cdjax (PYTHONPATH?): $(tail -n 1 "$out/import-error")"; exit 2
fi
stamp "pass start (limit ${limit}s, $module)"
pids=()
while IFS= read -r spec; do
  case "$spec" in ''|'#'*) continue ;; esac
  lane "$spec" & pids+=($!)
done < "$lanes"
rm -f "$out/.stopped"
( sleep "$limit"; touch "$out/.stopped"; stamp "time limit"; pkill -TERM -f "[${module:0:1}]${module:1}" ) &
killer=$!
wait "${pids[@]}"
kill "$killer" 2>/dev/null
stamp "pass done"
