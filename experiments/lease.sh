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
# The same wheels unpacked and packed as .whl-site/site.tar.xz (`pack_site` below, about 15 MB against .whl/'s 27 MB)
# are used where .whl/ is not carried: a device command carries 64 MiB at most, the working tree included (41 MB
# on 2026-11-25), so `carry: [".whl-site"]` leaves room that `[".whl"]` no longer does.
ensure_wheels() {
  local site=${SITE:-/tmp/site}
  if [ ! -d "$site/brax" ]; then
    if python3 -c "import brax, mujoco.mjx" 2>/dev/null; then return 0; fi
    if ls .whl/*.whl > /dev/null 2>&1; then
      python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$site" .whl/*.whl \
        || { echo "installing .whl/ into $site failed"; return 1; }
    elif [ -f .whl-site/site.tar.xz ]; then
      mkdir -p "$site" && tar -xJf .whl-site/site.tar.xz -C "$site" \
        || { echo "unpacking .whl-site/site.tar.xz into $site failed"; return 1; }
    else
      echo "brax and mujoco-mjx do not import and neither .whl/ nor .whl-site/ is here to install them from" \
        "(carry one)"; return 1
    fi
  fi
  export PYTHONPATH="$site:$PWD${PYTHONPATH:+:$PYTHONPATH}"
}

# pack_site: .whl-site/site.tar.xz from .whl/*.whl (run here, from the repository root, after
# ../shared/device/wheels.sh): each wheel unzipped into one directory, as `pip install --no-deps --target` lays it out
# (none of these wheels has a .data directory), then packed with xz (a minute or two on 2 cores).
pack_site() {
  local tmp
  tmp=$(mktemp -d) || return 1
  for w in .whl/*.whl; do
    python3 -c "import sys, zipfile; z = zipfile.ZipFile(sys.argv[1]); \
assert not any('.data/' in n for n in z.namelist()), sys.argv[1] + ' has a .data directory'; z.extractall(sys.argv[2])" \
      "$w" "$tmp" || { rm -rf "$tmp"; return 1; }
  done
  mkdir -p .whl-site && tar -cJf .whl-site/site.tar.xz -C "$tmp" . && rm -rf "$tmp" && ls -l .whl-site/site.tar.xz
}
