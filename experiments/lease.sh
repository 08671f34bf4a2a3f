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
# (none of these wheels has a .data directory), then packed with xz (a minute or two on 2 cores). Left out: the wheels
# no cdjax module imports, mujoco_studio (MuJoCo's GUI, 12.8 MB of wheel, 34 MB unpacked; `import mujoco` and
# mujoco.viewer do not load it: checked with mujoco 4.0.0 on Python 3.12), and the packages' own test data and tests
# (mujoco/mjx/test_data is 16 MB unpacked: robot meshes for MJX's tests; nothing in cdjax reads them). From the .whl/ of
# 2026-11-25 (43 MB, mujoco 4.0.0 split into mujoco, mujoco-core and mujoco-studio) the tarball is 10.8 MB (15.9 MB
# with MJX's test data, 23.1 MB with the GUI as well; the working tree grew to 51 MB on 2026-11-26, so only 10.8 fits): the
# ALE units carry it beside .whl-ale/ and .whl-atari/ (`carry_size .whl-site .whl-ale .whl-atari` says whether
# they fit). Since 2026-11-26 also left out: TensorFlow Probability's numpy substrate and its TensorFlow modules
# (tensorflow_probability/python/* but its __init__, internal/ and version.py: the jax substrate, which distrax imports,
# reads only these; distrax's distributions and cdjax's tests/test_learner.py checked against the pruned package on
# this machine), PyOpenGL's Windows DLLs and MuJoCo's documentation (mujoco/doc, reStructuredText), packed with
# xz -9e: 10.8 -> 9.2 MB, since the tracked tree (56 MB that day) and the 10.8 MB no longer fitted in 64 MiB together.
# The same day the kept logs became metrics.jsonl.xz (cdjax.io.write_packed): the tracked tree is 47.9 MB, so about
# 10 MB are left for the data units add; `carry_size .whl-site` says what is left before a call. On 2026-11-27 the
# tree (56.6 MB, 1,840 files with the tarball) no longer fitted beside it: `SITE_NO_GL=1 pack_site` leaves out PyOpenGL
# and glfw (8.4 MB instead of 9.2), enough for units that render nothing (the pixel and rendering units need them).
# On 2026-11-28 the tracked PNGs were re-encoded as palette images (`python -m experiments.compact_pngs`: 12.4 -> 6.1
# MB), and the full site fits again with about 5.8 MB to spare; run it on new figures before committing them.
pack_site() {
  local tmp w
  tmp=$(mktemp -d) || return 1
  for w in .whl/*.whl; do
    case "$(basename "$w")" in mujoco_studio-*) continue ;; esac
    python3 -c "import sys, zipfile; z = zipfile.ZipFile(sys.argv[1]); \
assert not any('.data/' in n for n in z.namelist()), sys.argv[1] + ' has a .data directory'; z.extractall(sys.argv[2])" \
      "$w" "$tmp" || { rm -rf "$tmp"; return 1; }
  done
  rm -rf "$tmp/mujoco/mjx/test_data" "$tmp/mujoco/sysid/tests" "$tmp/ml_collections/config_flags/tests" \
    "$tmp/tensorflow_probability/substrates/numpy" "$tmp/OpenGL/DLLS" "$tmp/mujoco/doc"
  if [ "${SITE_NO_GL:-0}" = 1 ]; then  # no rendering: 0.8 MB less (what fitted the 64 MiB on 2026-11-27)
    rm -rf "$tmp/OpenGL" "$tmp/glfw" "$tmp"/pyopengl-*.dist-info "$tmp"/glfw-*.dist-info
  fi
  find "$tmp/tensorflow_probability/python" -mindepth 1 -maxdepth 1 \
    ! -name __init__.py ! -name internal ! -name version.py -exec rm -rf {} +
  mkdir -p .whl-site && tar -cf - -C "$tmp" . | xz -9e -T2 > .whl-site/site.tar.xz && rm -rf "$tmp" && ls -l .whl-site/site.tar.xz
}

# ale_wheels: .whl-ale/ (ale-py 0.12.1, 3.1 MB; its wheel bundles the ROMs) and .whl-atari/ (gymnasium 1.3.0 and
# farama-notifications 0.0.6, 0.96 MB: what ale_py.vector_env imports; the GPU image has their other needs, numpy,
# cloudpickle and typing-extensions) for experiments/atari/device.sh, downloaded here (run from the repository root;
# the GPU machine reaches no package index); .gitignore keeps both out of git.
ale_wheels() {
  set -- --no-deps --only-binary=:all: --python-version 3.12 --implementation cp --platform manylinux_2_28_x86_64 \
    --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 --platform any
  python3 -m pip download -q "$@" -d .whl-ale ale-py==0.12.1 \
    && python3 -m pip download -q "$@" -d .whl-atari gymnasium==1.3.0 farama-notifications==0.0.6 \
    && ls -l .whl-ale .whl-atari
}

# carry_size [PATH ...]: the bytes a device call made from here (the repository root) would send, against its 64 MiB:
# the tracked files, the untracked ones git does not ignore, and the carried PATHs (the `carry` list). Returns 1 when
# they do not fit.
carry_size() {
  { git ls-files -z; git ls-files -z -o --exclude-standard; [ $# -gt 0 ] && find "$@" -type f -print0; } | python3 -c "
import os, sys
files = {f for f in sys.stdin.buffer.read().split(b'\0') if f and os.path.isfile(f)}
# as the device tool counts: each file as a tar member, a 512-byte header and its bytes in 512-byte blocks (the plain
# sum of sizes said 1.3 MB under on 2026-11-27 where the tool refused, 1,840 files)
n, limit = sum(512 + -(-os.path.getsize(f) // 512) * 512 for f in files), 64 * 2**20
print(f'{n:,} bytes ({n / 2**20:.1f} MiB) would travel, {limit - n:,} bytes under 64 MiB' if n <= limit
      else f'{n:,} bytes ({n / 2**20:.1f} MiB) would travel: {n - limit:,} bytes over 64 MiB')
sys.exit(n > limit)"
}
