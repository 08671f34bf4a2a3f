#!/usr/bin/env bash
# Sourced by the unit scripts of the experiments (experiments/paper_obs_space/device.sh, experiments/pixel/units.sh):
# a unit runs on a one-GPU device machine as one process session that outlives the device command (10 minutes at
# most), not the machine (gone 30 s after the last command returns), and is polled by calling the script again.
#
#   unit_run WORK CMD WAIT_S T0 AGAIN
#
# starts CMD once (setsid; its output in WORK/unit.log, its exit status in WORK/exit_code, WORK/started and
# WORK/command beside), then waits until WAIT_S seconds after T0 (the calling script's start, date +%s). Returns 0
# when CMD has ended; otherwise prints RUNNING, the command to call again (AGAIN) and the log's last lines, and
# returns 3.
unit_run() {
  local work=$1 cmd=$2 wait_s=$3 t0=$4 again=$5
  mkdir -p "$work"
  if [ ! -f "$work/started" ]; then
    nvidia-smi -L 2>/dev/null || true
    date +%s > "$work/started"
    echo "$cmd" > "$work/command"
    setsid bash -c "( $cmd ) > $work/unit.log 2>&1; echo \$? > $work/exit_code" < /dev/null > /dev/null 2>&1 &
    echo "STARTED at $(date -u +%H:%M:%S) UTC: $cmd"
  fi
  while [ ! -f "$work/exit_code" ]; do
    if [ $(( $(date +%s) - t0 )) -ge "$wait_s" ]; then
      echo "RUNNING: $(( $(date +%s) - $(cat "$work/started") )) s since it started; call again at once (the" \
        "machine goes back 30 s after a call):"
      echo "  $again"
      grep -v -i -E "warn|^\s*$" "$work/unit.log" | tail -n 6
      return 3
    fi
    sleep 5
  done
}

# ensure_wheels: the GPU image lacks brax and mujoco-mjx; install the wheels carried in .whl/ (run from the repository
# root) into $SITE (default /tmp/site) once per machine and put it and the repository on PYTHONPATH. Every call of a
# unit script runs it, so a poll that lands on a fresh machine (the last one gone) has the packages too. Does nothing
# where they import already. Returns 1, saying why, when they neither import nor can be installed.
ensure_wheels() {
  local site=${SITE:-/tmp/site}
  if [ ! -d "$site/brax" ]; then
    if python3 -c "import brax, mujoco.mjx" 2>/dev/null; then return 0; fi
    if ! ls .whl/*.whl > /dev/null 2>&1; then
      echo "brax and mujoco-mjx do not import and there is no .whl/ to install them from (carry .whl)"; return 1
    fi
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$site" .whl/*.whl \
      || { echo "installing .whl/ into $site failed"; return 1; }
  fi
  export PYTHONPATH="$site:$PWD${PYTHONPATH:+:$PYTHONPATH}"
}
