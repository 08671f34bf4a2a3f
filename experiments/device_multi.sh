#!/usr/bin/env bash
# Several units on one machine of several GPUs: one queue of units per GPU, each unit run by its setting's unit script
# as on a one-GPU machine (CUDA_VISIBLE_DEVICES=i), started once, polled, packed.
#
#   QUEUES="ant-2;halfcheetah-5;swimmer-1;swimmer-2 ant-4" bash experiments/device_multi.sh [WAIT_S]
#
# QUEUES: ';' separates the GPUs' queues (the first is GPU 0), ' ' the units of one queue, run one after another. A
# unit may be written UNIT:MIN_S[:VAR=VALUE...]: it is skipped unless at least MIN_S seconds (default 300) are left
# for its sweeps, and runs with the given environment (no spaces), e.g. halfcheetah-2:900:JAX_DEFAULT_MATMUL_PRECISION=highest.
# The unit script is UNIT_SCRIPT (default experiments/paper_obs_space/device.sh; experiments/pixel/units.sh and
# experiments/atari/device.sh take the same `SCRIPT UNIT WAIT_S` and pack $OUT/UNIT.tar.gz and $OUT/UNIT.log), for
# all units or per unit (UNIT:MIN_S:UNIT_SCRIPT=experiments/pixel/units.sh); what a script needs carried (.whl-site,
# .whl-ale, ...) the call carries.
# DEADLINE_S (default 1600): seconds after the first call's start by which every unit's sweeps stop. Each unit gets
# as its limit L = min(LIMIT_S (1260), what is left before the deadline less TAIL_S (180 s: its final evaluation,
# plots and packing, which the limit does not stop; the pixel units' take about 6 minutes)), passed as
# UNIT_ARGS="--limit L" (the observation-space units) and LIMIT_S=L, END_S=L+TAIL_S (the pixel and ALE units). A
# machine of several GPUs counts its whole held time against the session's device time (30 minutes, its start
# included; a one-GPU machine has at times counted less), so set the deadline from that, not from the 30-minute hold.
# The first call starts the queues (setsid: they outlive the call, not the machine); every call then waits up to
# WAIT_S seconds (default 560) until a unit it has not yet handed back is packed, copies that unit's UNIT.tar.gz and
# UNIT.log to $OUT, and says "RUNNING: call again" while any queue runs, else "ALL DONE". Call again at once: the
# machine goes back 30 s after a call. Each queue's log: runs/multi/queue-I.log.
set -u
here=$(dirname "$0")
root=runs/multi
packed=runs/units-out
out=${OUT:-$packed}
wait_s=${1:-560}
t0=$(date +%s)
. "$here/lease.sh"

if [ "${1:-}" = "--queue" ]; then  # one GPU's queue (started below)
  gpu=$2; deadline=$3
  for item in $(cat "$root/queue-$gpu"); do
    IFS=: read -ra parts <<< "$item"
    unit=${parts[0]}; min_s=${parts[1]:-300}; script=${UNIT_SCRIPT:-$here/paper_obs_space/device.sh}
    for kv in "${parts[@]:2}"; do case $kv in UNIT_SCRIPT=*) script=${kv#UNIT_SCRIPT=} ;; esac; done
    tail_s=${TAIL_S:-180}
    limit=$(( deadline - $(date +%s) - tail_s ))
    [ "$limit" -gt "${LIMIT_S:-1260}" ] && limit=${LIMIT_S:-1260}
    if [ "$limit" -lt "$min_s" ]; then
      echo "$(date -u +%H:%M:%S) skipped $unit: $limit s left, it needs $min_s" >> "$root/queue-$gpu.log"
      continue
    fi
    echo "$(date -u +%H:%M:%S) GPU $gpu: $unit ($script) with a limit of $limit s ${parts[*]:2}" >> "$root/queue-$gpu.log"
    env CUDA_VISIBLE_DEVICES="$gpu" OUT="$packed" UNIT_ARGS="--limit $limit" LIMIT_S="$limit" \
      END_S=$(( limit + tail_s )) "${parts[@]:2}" bash "$script" "$unit" 1000000 >> "$root/queue-$gpu.log" 2>&1
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
  unit=$(grep -E "^[0-9:]+ GPU" "$q.log" 2>/dev/null | tail -n 1 | awk '{print $4}')
  for log in runs/*units/"$unit"/unit.log; do
    [ -n "$unit" ] && [ -f "$log" ] && grep -v -i -E "warn|^\s*$" "$log" | tail -n 2
  done
done
if [ "$running" = 1 ]; then echo "RUNNING: call again at once: bash $0 $wait_s"; else echo "ALL DONE"; fi
ls -l "$out"
