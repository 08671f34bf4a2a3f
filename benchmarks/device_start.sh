#!/usr/bin/env bash
# Start a GPU job that outlives one device call (each call of the device tool is a fresh shell in a fresh copy of the
# working tree, at most 10 minutes; /tmp stays while the machine is held). From the repository root on the device:
#   bash benchmarks/device_start.sh NAME COMMAND [ARGS...]
# 1. installs the wheels of every carried `.whl*` directory into /tmp/site (pip --no-index --no-deps; those already
#    there are kept, so wheels carried in earlier calls count: carry the directories one call each when together
#    they pass the 64 MiB a call may carry);
# 2. refuses (status 2, one line) unless brax, mujoco.mjx and cdjax import with PYTHONPATH=/tmp/site:/tmp/code;
# 3. copies the code (cdjax, benchmarks, experiments, pyproject.toml) to /tmp/code, which later calls' copies of the
#    tree do not touch, and starts `cd /tmp/code && COMMAND ARGS` under setsid with that PYTHONPATH,
#    XLA_PYTHON_CLIENT_PREALLOCATE=false and PYTHONUNBUFFERED=1, its output in /tmp/NAME.log, its pid in /tmp/NAME.pid.
# Poll it with `bash benchmarks/device_poll.sh NAME [WAIT] [DIR...]`. Without COMMAND it only installs and checks (a
# first call that carries some of the wheels).
set -u
name=${1:?job name}
shift
export PYTHONPATH=/tmp/site:/tmp/code XLA_PYTHON_CLIENT_PREALLOCATE=false PYTHONUNBUFFERED=1
shopt -s nullglob
wheels=(.whl*/*.whl)
if [ ${#wheels[@]} -gt 0 ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site "${wheels[@]}" \
    2>&1 | grep -vE "WARNING: (Running pip as|Target directory)" | tail -n 3
fi
[ $# -eq 0 ] && { echo "installed ${#wheels[@]} wheel(s) into /tmp/site"; exit 0; }
rm -rf /tmp/code && mkdir -p /tmp/code && cp -r cdjax benchmarks experiments pyproject.toml /tmp/code/ || exit 2
if ! (cd /tmp/code && python3 -c "import brax, mujoco.mjx, cdjax") > "/tmp/$name.import" 2>&1; then
  echo "not started: $(tail -n 1 "/tmp/$name.import") (carry the missing wheels first)"; exit 2
fi
# setsid forks when the shell made the job a process-group leader, so the job writes its own pid before it execs
cd /tmp/code && setsid nohup bash -c 'echo $$ > "$0"; exec "$@"' "/tmp/$name.pid" "$@" > "/tmp/$name.log" 2>&1 < /dev/null &
sleep 1
echo "started $name (pid $(cat "/tmp/$name.pid")): $*"
