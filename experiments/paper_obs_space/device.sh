#!/usr/bin/env bash
# One unit of the observation-space experiment on a one-GPU machine: started once, polled, packed (PLAN.md).
#
#   bash experiments/paper_obs_space/device.sh UNIT [WAIT_S]
#
# The first call starts `python -m experiments.paper_obs_space train --unit UNIT` as its own process session
# (setsid: it outlives the call, not the machine) in runs/units/UNIT/ and waits. Every call waits up to WAIT_S
# seconds (default 560: a device command may run 10 minutes) for the unit to end, then says either
# "RUNNING: call again" (call the same command again at once: the machine goes back 30 s after a call) or
# "DONE", after packing into $OUT (default runs/units-out):
#   UNIT.tar.gz  the unit's run directories without checkpoints and TensorBoard files, metrics thinned and
#                xz-compressed (experiments.thin_logs), with run.json, phase.jsonl, eval.jsonl, machine.json, log.txt,
#                summary.md and the unit's unit.json (commands, exit codes, wall-clock)
#   UNIT.log     the unit's whole output
# The unit's sweeps stop by their --time-limit (train --limit, 1260 s from the unit's start, compile included);
# each then evaluates and plots (a minute or two). UNIT_ARGS holds more `train` options (e.g. --steps for a try).
# The GPU image has no `cdjax` console script: everything runs as python -m.
set -u
unit=$1; wait_s=${2:-560}
work=runs/units/$unit
out=${OUT:-runs/units-out}
mkdir -p "$work" "$out"
t0=$(date +%s)
export PYTHONUNBUFFERED=1
. "$(dirname "$0")/../lease.sh"
ensure_wheels || exit 1
unit_run "$work" "python -m experiments.paper_obs_space train --unit $unit --out $work ${UNIT_ARGS:-}" "$wait_s" "$t0" \
  "bash experiments/paper_obs_space/device.sh $unit" || exit 0
thin=runs/units-thin
rm -rf "${thin:?}/$unit" && python -m experiments.thin_logs "$work" "$thin/$unit" >/dev/null
mkdir -p "$thin/$unit"  # a unit that died before writing a run directory still packs its unit.json
cp "$work/unit.json" "$thin/$unit/" 2>/dev/null
tar -czf "$out/$unit.tar.gz" -C "$thin" "$unit"
cp "$work/unit.log" "$out/$unit.log"
echo "DONE: unit $unit, exit status $(cat "$work/exit_code"), $(( $(date +%s) - $(cat "$work/started") )) s since it started"
ls -l "$out"
grep -v -i -E "warn|^\s*$" "$work/unit.log" | grep -E "Trained in|Evaluation|phase of|Stopped|Done:|cdjax:" | tail -n 20
