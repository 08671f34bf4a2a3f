#!/usr/bin/env bash
# A2C vs A2C + consistency on Atari, on a GPU machine. Two forms:
#
#   bash experiments/atari/device.sh ale-GAME [WAIT_S]            # an ALE tier unit: one game inside one lease
#   bash experiments/atari/device.sh --print-command ale-GAME     # its command line; nothing started or installed
#   bash experiments/atari/device.sh OUT SECONDS [GAME ...] [-- extra `cdjax sweep` options]   # within one call
#
# ALE tier unit (issue 23; GAME: breakout, seaquest, mspacman or frostbite; experiments/atari/RESULTS.md gives the
# device calls): `cdjax sweep --setting atari --preset GAME --arms a2c a2c-cd --seeds 3 --steps $ALE_STEPS` (default
# 1,000,000 agent steps = 4M frames per run; the 3 seeds' 48 emulators one ale-py vector environment, one thread per
# CPU core: one unit per machine) started by the first call as its own process session (setsid, experiments/lease.sh
# unit_run: it outlives the call, not the machine) in runs/atari-units/ale-GAME/. Every call waits up to WAIT_S
# seconds (default 560: a device command runs 10 minutes at most) for the unit to end, then says "RUNNING: call
# again" (call the same command again at once: the machine goes back 30 s after a call) or "DONE" after packing into
# $OUT (default runs/atari-units-out):
#   ale-GAME.tar.gz          the run directory GAME/ without checkpoints (run.json, eval.jsonl, summary.md, log.txt
#                            (the unit's output), metrics.jsonl.xz thinned by experiments.thin_logs keeping each
#                            run's last 1,250 updates whole, the last 10% of 1M agent steps that its final return
#                            averages)
#   ale-GAME-results.md, ale-GAME-curves.png   experiments.atari.report's table and figure of the game
#   ale-GAME.log             the unit's whole output
# The sweep stops by its own --time-limit (LIMIT_S, default 1080 s from its start, compile included: 6M agent steps
# need about 6k/s, the benchmark measured 7-10k at 16 to 64 emulators), checkpointed, before a chunk (250 updates,
# about 8 s per arm) that would end later; its hang guard (timeout) is 120 s later. Then every run is evaluated at its
# last checkpoint (`cdjax eval --episodes 100`, sampled actions) within EVAL_S (default 360 s), fewer where it would
# end past END_S - 120 s (END_S default 1380 s, 23 minutes, from the unit's start: the lease's 30 less the machine's
# start, the installs and the packing), at least 60 s; then `cdjax plot` (summary.md) and the report, 50 s each at
# most. A unit that stops short of the budget is reported at the steps both arms reached. Typical: 11-15 minutes of
# training, 2-4 of evaluation (not yet timed at this size: 300 emulators per arm play until the longest of their
# episodes ends; one cut short leaves the report's eval column n/a and the training curves whole), under a minute of
# report and packing.
# Each call first installs what the machine lacks: ensure_wheels (.whl-site/ or .whl/), then gymnasium from
# .whl-atari/ and ale-py from .whl-ale/. Carry [".whl-site", ".whl-ale", ".whl-atari"], built here by
# ../shared/device/wheels.sh, then `. experiments/lease.sh; pack_site; ale_wheels` (`carry_size .whl-site .whl-ale
# .whl-atari` says whether they fit: 58.2 MiB on 2026-11-25).
# SWEEP_ARGS holds more `cdjax sweep` options (e.g. "--steps 20000 --chunk-updates 25" for a try).
#
# Within one call (MinAtar, and the old ALE path): A2C vs A2C + consistency on MinAtar games (10 seeds vmapped per
# arm) or ALE games (3 seeds, their emulators one ale-py vector environment), stopped after a time limit; logs, an
# evaluation over 100 episodes per run, the report (table + figure) and a tarball of the run directories. The whole
# script takes about SECONDS, SECONDS + 180 at most where a process hangs (the guards: the training time + 120 s and a
# 60-s kill for a sweep, EVAL_RESERVE for its evaluation): in one 600-s device command, SECONDS at most 420.
#
# GAMEs are MinAtar games (default: breakout seaquest), each run as `python -m cdjax.cli sweep --setting atari
# --preset minatar-GAME`, or ALE games named ale-GAME (ale-breakout, ale-seaquest, ale-mspacman, ale-frostbite:
# `--preset GAME --steps $ALE_STEPS`, default 1,000,000 agent steps = 4M frames per run, the ALE tier's budget). Game i
# runs on GPU i mod (number of GPUs); games sharing a GPU split its memory. An ALE game steps its emulators with one
# thread per CPU core: give it the host alone (one ALE game per call). Extra options after -- go to every sweep (e.g.
# -- --steps 2000000). Training gets SECONDS minus EVAL_RESERVE (default 240; at least 60): each sweep's --time-limit
# stops it, checkpointed, before a chunk that would end later; a run stopped early is then evaluated at its last
# checkpoint (`cdjax eval --episodes 100`), unless EVAL=0 (a call that another call will continue: the last one
# evaluates).
# The packages the machine lacks are installed as for a unit (carry .whl-site or .whl, and .whl-atari; .whl-ale too for
# ALE games).
# OUT/GAME.log: the output of each game; OUT/runs/GAME: the run directory; OUT/report: RESULTS table and figure;
# OUT/runs.tar.gz: the run directories without checkpoints, their metrics thinned (experiments.thin_logs; an ALE run
# keeps its last 1,250 updates whole, the last 10% of 1M agent steps, which its final return averages).
# Called again with the same OUT, a game whose run exists is continued (--resume; an ALE game's emulators start
# new games, see cdjax.agents.atari.ale). The memory share of each process is MEM_FRACTION (default 0.9 / the
# games per GPU): lower it to leave room for other work on the same GPU.
set -u
. "$(dirname "$0")/../lease.sh"

# atari_packages [ale]: gymnasium (what gymnax and ale_py.vector_env import) from .whl-atari/, gymnax (with what it
# imports beyond the image) from .whl/ or .whl-atari/ where ensure_wheels did not bring it, and with `ale` ale-py from
# .whl-ale/ (or .whl/, .whl-atari/), each only where it does not import. Returns 1, saying what to carry, otherwise.
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

# An ALE tier unit: the first argument --print-command, or ale-GAME with at most a WAIT_S after it.
if [ "${1:-}" = --print-command ] || { [[ ${1:-} == ale-* ]] && [ $# -le 2 ]; }; then
  print_only=0
  if [ "$1" = --print-command ]; then print_only=1; shift; fi
  unit=${1:?usage: device.sh [--print-command] ale-GAME [WAIT_S]}; wait_s=${2:-560}
  game=${unit#ale-}
  case "$unit" in
    ale-breakout|ale-seaquest|ale-mspacman|ale-frostbite) ;;
    *) echo "unknown ALE unit $unit: ale-breakout, ale-seaquest, ale-mspacman or ale-frostbite" >&2; exit 2 ;;
  esac
  work=runs/atari-units/$unit
  run=$work/$game
  out=${OUT:-runs/atari-units-out}
  limit=${LIMIT_S:-1080}
  end=${END_S:-1380}
  eval_max=${EVAL_S:-360}
  t0=$(date +%s)
  # the seconds left for the evaluation when it starts: END_S from the unit's start, less 120 for plot and report
  eval_s="\$(( $end - \$(date +%s) + \$(cat $work/started) - 120 ))"
  cmd="timeout -s INT -k 60 $(( limit + 120 )) python -m cdjax.cli sweep --setting atari --preset $game"
  cmd="$cmd --arms a2c a2c-cd --seeds 3 --steps ${ALE_STEPS:-1000000} --no-progress --no-final-eval"
  cmd="$cmd --time-limit $limit --out $run ${SWEEP_ARGS:-}; s=$eval_s;"
  cmd="$cmd timeout -k 10 \$(( s > $eval_max ? $eval_max : s < 60 ? 60 : s )) python -m cdjax.cli eval $run"
  cmd="$cmd --episodes 100; timeout -k 10 50 python -m cdjax.cli plot $run;"
  cmd="$cmd timeout -k 10 50 python -m experiments.atari.report $run --out $work/report"
  if [ "$print_only" = 1 ]; then echo "$cmd"; exit 0; fi
  mkdir -p "$work" "$out"
  export PYTHONUNBUFFERED=1
  ensure_wheels || exit 1  # brax, mujoco-mjx, distrax, gymnax: from .whl/ or .whl-site/ (carry one)
  atari_packages ale || exit 1
  unit_run "$work" "$cmd" "$wait_s" "$t0" "bash experiments/atari/device.sh $unit" || exit 0
  thin=runs/atari-units-thin/$unit
  rm -rf "$thin" && mkdir -p "$thin/$game"  # a unit that died before its run directory still packs its log
  [ -f "$run/run.json" ] && python -m experiments.thin_logs "$run" "$thin/$game" --points 1500 --tail 1250 >/dev/null
  cp "$work/unit.log" "$thin/$game/log.txt"
  tar -czf "$out/$unit.tar.gz" -C "$thin" "$game"
  cp "$work/unit.log" "$out/$unit.log"
  for f in results.md curves.png; do [ -f "$work/report/$f" ] && cp "$work/report/$f" "$out/$unit-$f"; done
  echo "DONE: unit $unit, exit status $(cat "$work/exit_code"), $(( $(date +%s) - $(cat "$work/started") )) s since" \
    "it started"
  ls -l "$out"
  grep -v -i -E "warn|^\s*$" "$work/unit.log" | grep -E "Trained in|Stopped|stopped|Evaluat|eval/|Wrote|Error|error" \
    | tail -n 20
  cat "$work/report/results.md" 2>/dev/null | tail -n 12
  exit 0
fi

# Within one call.
out=$1; limit=$2; shift 2
games=(); while [ $# -gt 0 ] && [ "$1" != "--" ]; do games+=("$1"); shift; done
[ "${1:-}" = "--" ] && shift
[ ${#games[@]} -eq 0 ] && games=(breakout seaquest)
reserve=${EVAL_RESERVE:-240}
train=$(( limit - reserve )); [ "$train" -lt 60 ] && train=60
mkdir -p "$out/runs"
ensure_wheels || exit 1  # brax, mujoco-mjx, distrax, gymnax: from .whl/ or .whl-site/ (carry one)
if printf '%s\n' "${games[@]}" | grep -q '^ale-'; then atari_packages ale || exit 1; else atari_packages || exit 1; fi
ngpu=$(nvidia-smi -L 2>/dev/null | wc -l); [ "$ngpu" -lt 1 ] && ngpu=1
share=$(( (${#games[@]} + ngpu - 1) / ngpu ))
fraction=${MEM_FRACTION:-$(python -c "print(round(0.9 / $share, 2))")}
t0=$(date +%s)
evals_before() { local n; n=$(grep -c '"episodes": 100' "$out/runs/$1/eval.jsonl" 2>/dev/null); echo "${n:-0}"; }
declare -A before
for g in "${games[@]}"; do before[$g]=$(evals_before "$g"); done
pids=()
for i in "${!games[@]}"; do
  g=${games[$i]}
  case $g in ale-*) preset=(--preset "${g#ale-}" --steps "${ALE_STEPS:-1000000}") ;; *) preset=(--preset "minatar-$g") ;; esac
  if [ -f "$out/runs/$g/run.json" ]; then  # a run of an earlier call: continue it
    what=(sweep --out "$out/runs/$g" --resume --no-progress --time-limit "$train")
  else
    what=(sweep --setting atari "${preset[@]}" --out "$out/runs/$g" --no-progress --time-limit "$train" "$@")
  fi
  # timeout only guards against a hang: --time-limit stops the sweep between chunks
  CUDA_VISIBLE_DEVICES=$(( i % ngpu )) XLA_PYTHON_CLIENT_MEM_FRACTION=$fraction timeout -s INT -k 60 $(( train + 120 )) \
    python -m cdjax.cli "${what[@]}" >>"$out/$g.log" 2>&1 &
  pids+=($!)
done
for p in "${pids[@]}"; do wait "$p"; done
echo "training took $(( $(date +%s) - t0 )) s"
pids=()
for i in "${!games[@]}"; do  # the evaluations of runs stopped before their final one, side by side
  g=${games[$i]}
  if [ "${EVAL:-1}" = 1 ] && [ "$(evals_before "$g")" -le "${before[$g]}" ]; then  # stopped before its final evaluation
    CUDA_VISIBLE_DEVICES=$(( i % ngpu )) XLA_PYTHON_CLIENT_MEM_FRACTION=$fraction timeout -k 30 $(( reserve > 210 ? reserve - 30 : 180 )) \
      python -m cdjax.cli eval "$out/runs/$g" --episodes 100 >>"$out/$g.log" 2>&1 &
    pids+=($!)
  fi
done
for p in "${pids[@]}"; do wait "$p"; done
for g in "${games[@]}"; do echo "== $g"; tail -n 5 "$out/$g.log"; done
python -m experiments.atari.report "$out"/runs/* --out "$out/report" 2>&1 | tail -n 30
# what comes back: the run directories with thinned metrics (experiments.thin_logs; a full MinAtar log is ~150 MB)
rm -rf "$out/thin"
for g in "${games[@]}"; do
  case $g in ale-*) keep=(--points 1500 --tail 1250) ;; *) keep=() ;; esac
  [ -d "$out/runs/$g" ] && python -m experiments.thin_logs "$out/runs/$g" "$out/thin/runs/$g" ${keep[@]+"${keep[@]}"} >/dev/null
  cp "$out/$g.log" "$out/thin/runs/$g/log.txt" 2>/dev/null
done
tar -czf "$out/runs.tar.gz" -C "$out/thin" runs
echo "total $(( $(date +%s) - t0 )) s"
