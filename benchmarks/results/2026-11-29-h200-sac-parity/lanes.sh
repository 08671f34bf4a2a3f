#!/usr/bin/env bash
# Parity units as lanes: each line of LANES is one lane, its jobs separated by ";;" and run one after another;
# a job is "NAME ARGS...", run as `python -m benchmarks.brax_sac ARGS --out OUT/NAME > OUT/NAME.log`. Lanes run
# side by side (so rows measure returns at equal env steps, not speed). Everything stops after LIMIT seconds; a job
# whose OUT/NAME/rows.jsonl already holds its final row is skipped, so a later loan reruns only what did not finish.
#   setsid bash benchmarks/results/2026-11-29-h200-sac-parity/lanes.sh OUT LANES [LIMIT]
set -u
out=${1:?output directory}
lanes=${2:?lane file}
limit=${3:-1400}
mkdir -p "$out"
export XLA_PYTHON_CLIENT_PREALLOCATE=false
stamp() { echo "$1 $(date -u +%T)" >> "$out/progress"; }
lane() {
  local line=$1 job name
  while [ -n "$line" ]; do
    job=${line%%;;*}
    if [ "$job" = "$line" ]; then line=""; else line=${line#*;;}; fi
    read -r name args <<< "$job"
    [ -z "$name" ] && continue
    if [ -f "$out/$name/done" ]; then stamp "skip $name (done)"; continue; fi
    stamp "start $name"
    # shellcheck disable=SC2086
    python -m benchmarks.brax_sac $args --out "$out/$name" > "$out/$name.log" 2>&1
    rc=$?
    [ $rc -eq 0 ] && touch "$out/$name/done"
    stamp "end $name rc=$rc"
  done
}
if ! python -c "import brax, mujoco.mjx, cdjax" 2> "$out/import-error"; then  # a lane of failed jobs is a lost loan
  stamp "cannot import brax, mujoco.mjx or cdjax (PYTHONPATH?): $(tail -n 1 "$out/import-error")"; exit 2
fi
stamp "pass start (limit ${limit}s)"
pids=()
while IFS= read -r spec; do
  case "$spec" in ''|'#'*) continue ;; esac
  lane "$spec" & pids+=($!)
done < "$lanes"
( sleep "$limit"; stamp "time limit"; pkill -TERM -f "[b]enchmarks.brax_sac" ) &
killer=$!
wait "${pids[@]}"
kill "$killer" 2>/dev/null
stamp "pass done"
