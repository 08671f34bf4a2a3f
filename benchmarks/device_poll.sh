#!/usr/bin/env bash
# Poll a job of benchmarks/device_start.sh and bring its results back, in one device call:
#   bash benchmarks/device_poll.sh NAME [WAIT] [DIR...]
# waits up to WAIT seconds (default 0) while the job runs, then prints whether it still runs, the last lines of
# /tmp/NAME.log and of every DIR/progress, and packs /tmp/NAME.log and the DIRs (paths under /tmp) into
# $OUT/NAME.tgz, so that each poll brings back everything so far (the machine goes back when idle, and with it /tmp),
# but checkpoints (folders named checkpoints*: too large to come back, and of no use once the machine is gone).
set -u
name=${1:?job name}
wait=${2:-0}
shift $(( $# < 2 ? $# : 2 ))
pid=$(cat "/tmp/$name.pid" 2>/dev/null || echo 0)
end=$(( $(date +%s) + wait ))
while [ "$pid" -gt 0 ] && kill -0 "$pid" 2>/dev/null && [ "$(date +%s)" -lt "$end" ]; do sleep 5; done
if [ "$pid" -gt 0 ] && kill -0 "$pid" 2>/dev/null; then echo "$name: running"; else echo "$name: ended"; fi
tail -n 5 "/tmp/$name.log" 2>/dev/null
for d in "$@"; do [ -f "$d/progress" ] && { echo "== $d/progress"; tail -n 8 "$d/progress"; }; done
if [ -n "${OUT:-}" ]; then
  paths=("$name.log")
  for d in "$@"; do paths+=("${d#/tmp/}"); done
  tar czf "$OUT/$name.tgz" -C /tmp --ignore-failed-read --exclude='checkpoints*' "${paths[@]}" 2>/dev/null
  echo "packed $(du -h "$OUT/$name.tgz" | cut -f1) into \$OUT/$name.tgz"
fi
