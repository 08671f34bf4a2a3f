#!/usr/bin/env bash
# Several units of the observation-space experiment on one machine of several GPUs: one queue of units per GPU,
# each unit run by device.sh as on a one-GPU machine (CUDA_VISIBLE_DEVICES=i), started once, polled, packed.
#
#   QUEUES="ant-2;halfcheetah-5;swimmer-1;swimmer-2 ant-4" bash experiments/paper_obs_space/device_multi.sh [WAIT_S]
#
# QUEUES: ';' separates the GPUs' queues (the first is GPU 0), ' ' the units of one queue, run one after another. A
# unit may be written UNIT:MIN_S[:VAR=VALUE...]: it is skipped unless at least MIN_S seconds are left for its sweeps,
# and runs with the given environment (e.g. halfcheetah-2:900:JAX_DEFAULT_MATMUL_PRECISION=highest).
# DEADLINE_S (default 1600): seconds after the first call's start by which every unit's sweeps stop; each unit gets
# `--limit` = min(LIMIT_S (1260), what is left before the deadline less TAIL_S (180 s: its final evaluation, plots and
# packing, which the limit does not stop)). A multi-GPU machine counts its whole held time against the session's
# device time (30 minutes, its start included), so the deadline is set from that, not from the 30-minute hold.
# The first call starts the queues (setsid: they outlive the call, not the machine); every call then waits up to
# WAIT_S seconds (default 560) until a unit it has not yet handed back is packed, copies that unit's UNIT.tar.gz and
# UNIT.log (device.sh's) to $OUT, and says "RUNNING: call again" while any queue runs, else "ALL DONE". Call again at
# once: the machine goes back 30 s after a call.
set -u
here=$(dirname "$0")
root=runs/multi
packed=runs/units-out
out=${OUT:-$packed}
wait_s=${1:-560}
t0=$(date +%s)
. "$here/../lease.sh"

if [ "${1:-}" = "--queue" ]; then  # one GPU's queue (started below)
  gpu=$2; deadline=$3
  for item in $(cat "$root/queue-$gpu"); do
    IFS=: read -ra parts <<< "$item"
    unit=${parts[0]}; min_s=${parts[1]:-300}
    limit=$(( deadline - $(date +%s) - ${TAIL_S:-180} ))
    [ "$limit" -gt "${LIMIT_S:-1260}" ] && limit=${LIMIT_S:-1260}
    if [ "$limit" -lt "$min_s" ]; then
      echo "$(date -u +%H:%M:%S) skipped $unit: $limit s left, it needs $min_s" >> "$root/queue-$gpu.log"
      continue
    fi
    echo "$(date -u +%H:%M:%S) GPU $gpu: $unit with --limit $limit ${parts[*]:2}" >> "$root/queue-$gpu.log"
    env CUDA_VISIBLE_DEVICES="$gpu" OUT="$packed" UNIT_ARGS="--limit $limit" "${parts[@]:2}" \
      bash "$here/device.sh" "$unit" 1000000 >> "$root/queue-$gpu.log" 2>&1
  done
  echo "$(date -u +%H:%M:%S) queue done" >> "$root/queue-$gpu.log"
  touch "$root/queue-$gpu.done"
  exit 0
fi

ensure_wheels || exit 1
mkdir -p "$root" "$packed" "$out"
if [ ! -f "$root/started" ]; then
  [ -n "${QUEUES:-}" ] || { echo "QUEUES names the units, one queue per GPU, e.g. QUEUES=\"ant-2;swimmer-1 ant-4\""; exit 2; }
  nvidia-smi -L 2>/dev/null || true
  date +%s > "$root/started"
  deadline=$(( t0 + ${DEADLINE_S:-1600} ))
  IFS=';' read -ra queues <<< "$QUEUES"
  for gpu in "${!queues[@]}"; do
    echo "${queues[$gpu]}" > "$root/queue-$gpu"
    setsid bash "$0" --queue "$gpu" "$deadline" < /dev/null > /dev/null 2>&1 &
    echo "STARTED GPU $gpu: ${queues[$gpu]}"
  done
  sleep 2
fi

hand_back() {  # copies every unit packed and not yet handed back to $OUT; prints their names
  local f unit
  for f in "$packed"/*.tar.gz; do
    [ -f "$f" ] || continue
    unit=$(basename "$f" .tar.gz)
    [ -f "$root/sent-$unit" ] && continue
    [ "$out" != "$packed" ] && cp "$f" "$packed/$unit.log" "$out/"
    touch "$root/sent-$unit"; echo "$unit"
  done
}

while true; do
  sent=$(hand_back)
  running=0
  for q in "$root"/queue-?; do [ -f "$q.done" ] || running=1; done
  if [ -n "$sent" ] || [ "$running" = 0 ] || [ $(( $(date +%s) - t0 )) -ge "$wait_s" ]; then break; fi
  sleep 5
done
echo "$(( $(date +%s) - $(cat "$root/started") )) s since the queues started"
[ -n "$sent" ] && echo "HANDED BACK: $sent"
for q in "$root"/queue-?; do
  echo "--- ${q##*/}: $(cat "$q")"; grep -E "^[0-9:]+ (GPU|skipped|queue done)|^DONE" "$q.log" 2>/dev/null | tail -n 4
  unit=$(grep -E "^[0-9:]+ GPU" "$q.log" 2>/dev/null | tail -n 1 | awk '{print $4}' | tr -d :)
  [ -n "$unit" ] && [ -f "runs/units/$unit/unit.log" ] && grep -v -i -E "warn|^\s*$" "runs/units/$unit/unit.log" | tail -n 2
done
if [ "$running" = 1 ]; then echo "RUNNING: call again at once: bash $0 $wait_s"; else echo "ALL DONE"; fi
ls -l "$out"
