#!/usr/bin/env bash
# Sourced before a unit runs on a GPU machine whose image lacks packages and reaches no package index (the leased
# machines of this project): installs the wheels carried beside the working tree. Elsewhere (a SLURM cluster, a
# workstation) install cdjax's dependencies as usual and leave this out.
#
#   . experiments/wheels.sh && ensure_wheels && python -m experiments.launch start ...
#   . experiments/wheels.sh && ensure_wheels && atari_packages ale && python -m experiments.atari run ale-breakout ...
#
# Here, before the call: ../shared/device/wheels.sh (the wheels into .whl/), then `pack_site` (.whl-site/site.tar.xz,
# smaller than .whl/, for a call's carry limit) and for the Atari units `ale_wheels`; `carry_size .whl-site` says
# whether the tracked tree and the carried paths fit a call.

# ensure_wheels: the GPU image lacks brax and mujoco-mjx; install the wheels carried in .whl/ (run from the repository
# root) into $SITE (default /tmp/site) once per machine and put it and the repository on PYTHONPATH. Run it in every
# call, so a call that lands on a fresh machine has the packages too. Does nothing where they import already.
# Returns 1, saying why, when they neither import nor can be installed. The same wheels unpacked and packed as
# .whl-site/site.tar.xz (`pack_site`) are used where .whl/ is not carried.
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

# pack_site: .whl-site/site.tar.xz from .whl/*.whl (run from the repository root): each wheel unzipped into one
# directory, as `pip install --no-deps --target` lays it out (none of these wheels has a .data directory), packed with
# xz -9e. Left out: what no cdjax module imports: mujoco_studio (MuJoCo's GUI; `import mujoco` and mujoco.viewer do not
# load it), the packages' own tests and test data (MJX's robot meshes), TensorFlow Probability's numpy substrate and
# TensorFlow modules (the jax substrate, which distrax imports, reads only __init__, internal/ and version.py),
# PyOpenGL's Windows DLLs and MuJoCo's documentation; with SITE_NO_GL=1 PyOpenGL and glfw too (units that render
# nothing: not the pixel units).
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
  if [ "${SITE_NO_GL:-0}" = 1 ]; then
    rm -rf "$tmp/OpenGL" "$tmp/glfw" "$tmp"/pyopengl-*.dist-info "$tmp"/glfw-*.dist-info
  fi
  find "$tmp/tensorflow_probability/python" -mindepth 1 -maxdepth 1 \
    ! -name __init__.py ! -name internal ! -name version.py -exec rm -rf {} +
  mkdir -p .whl-site && tar -cf - -C "$tmp" . | xz -9e -T2 > .whl-site/site.tar.xz && rm -rf "$tmp" && ls -l .whl-site/site.tar.xz
}

# ale_wheels: .whl-ale/ (ale-py 0.12.1; its wheel bundles the ROMs) and .whl-atari/ (gymnasium 1.3.0 and
# farama-notifications 0.0.6: what ale_py.vector_env imports; the GPU image has their other needs, numpy, cloudpickle
# and typing-extensions) for the Atari units, downloaded here (run from the repository root; the GPU machine reaches
# no package index); .gitignore keeps both out of git.
ale_wheels() {
  set -- --no-deps --only-binary=:all: --python-version 3.12 --implementation cp --platform manylinux_2_28_x86_64 \
    --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 --platform any
  python3 -m pip download -q "$@" -d .whl-ale ale-py==0.12.1 \
    && python3 -m pip download -q "$@" -d .whl-atari gymnasium==1.3.0 farama-notifications==0.0.6 \
    && ls -l .whl-ale .whl-atari
}

# atari_packages [ale]: on the GPU machine, after ensure_wheels: gymnasium (what gymnax and ale_py.vector_env import)
# from .whl-atari/, gymnax (with what it imports beyond the image) from .whl/ or .whl-atari/ where ensure_wheels did
# not bring it, and with `ale` ale-py from .whl-ale/ (or .whl/, .whl-atari/), each only where it does not import.
# Returns 1, saying what to carry, otherwise.
atari_packages() {
  if ! python -c "import gymnasium" 2>/dev/null; then  # .whl-site holds gymnax, not it
    python -m pip install --quiet --no-index --no-deps --find-links .whl-atari gymnasium==1.3.0 \
      farama-notifications==0.0.6 || { echo "gymnasium is missing: carry .whl-atari"; return 1; }
  fi
  if ! python -c "import gymnax" 2>/dev/null; then
    python -m pip install --quiet --no-index --no-deps --find-links .whl --find-links .whl-atari gymnax==1.0.1 \
      seaborn==0.13.2 cloudpickle==3.1.2 || { echo "gymnax is missing: carry .whl (or .whl-site)"; return 1; }
  fi
  if [ "${1:-}" = ale ] && ! python -c "import ale_py" 2>/dev/null; then
    python -m pip install --quiet --no-index --no-deps --find-links .whl --find-links .whl-atari --find-links .whl-ale \
      ale-py==0.12.1 || { echo "ale-py is missing: carry .whl-ale (or .whl) holding its wheel"; return 1; }
  fi
}

# carry_size [PATH ...]: the bytes a device call made from here (the repository root) would send, against its 64 MiB:
# the tracked files, the untracked ones git does not ignore, and the carried PATHs (the `carry` list). Returns 1 when
# they do not fit.
carry_size() {
  { git ls-files -z; git ls-files -z -o --exclude-standard; [ $# -gt 0 ] && find "$@" -type f -print0; } | python3 -c "
import os, sys
files = {f for f in sys.stdin.buffer.read().split(b'\0') if f and os.path.isfile(f)}
# as the device tool counts: each file as a tar member, a 512-byte header and its bytes in 512-byte blocks
n, limit = sum(512 + -(-os.path.getsize(f) // 512) * 512 for f in files), 64 * 2**20
print(f'{n:,} bytes ({n / 2**20:.1f} MiB) would travel, {limit - n:,} bytes under 64 MiB' if n <= limit
      else f'{n:,} bytes ({n / 2**20:.1f} MiB) would travel: {n - limit:,} bytes over 64 MiB')
sys.exit(n > limit)"
}
