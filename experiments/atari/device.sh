#!/usr/bin/env bash
# A2C vs A2C + consistency on MinAtar games (10 seeds vmapped per arm) or ALE games (3 seeds, their emulators one
# ale-py vector environment), stopped after a time limit; logs, an evaluation over 100 episodes per run, the report
# (table + figure) and a tarball of the run directories.
#
#   bash experiments/atari/device.sh OUT SECONDS [GAME ...] [-- extra `cdjax sweep` options]
#
# GAMEs are MinAtar games (default: breakout seaquest), each run as `python -m cdjax.cli sweep --setting atari
# --preset minatar-GAME`, or ALE games named ale-GAME (ale-breakout, ale-seaquest, ale-mspacman, ale-frostbite:
# `--preset GAME --steps $ALE_STEPS`, default 1,000,000 agent steps = 4M frames per run, the ALE tier's budget; ale-py is
# installed from ./.whl or ./.whl-ale when missing: carry one of them). Game i runs on GPU i mod (number of GPUs);
# games sharing a GPU split its memory. An ALE game steps its emulators with one thread per CPU core: give it the host
# alone (one ALE game per call). Extra options after -- go to every sweep (e.g. -- --steps 2000000). Training gets
# SECONDS minus EVAL_RESERVE (default 240; at least 60): each sweep's --time-limit stops it, checkpointed, before a chunk
# that would end later; a run stopped early is then evaluated at its last checkpoint (`cdjax eval --episodes 100`),
# unless EVAL=0 (a call that another call will continue: the last one evaluates).
# The whole script takes about SECONDS. gymnax is installed from ./.whl when the image lacks it.
# OUT/GAME.log: the output of each game; OUT/runs/GAME: the run directory; OUT/report: RESULTS table and figure;
# OUT/runs.tar.gz: the run directories without checkpoints, their metrics thinned (experiments.thin_logs; an ALE run
# keeps its last 1,250 updates whole, the last 10% of 1M agent steps, which its final return averages).
# Called again with the same OUT, a game whose run exists is continued (--resume; an ALE game's emulators start
# new games, see cdjax.agents.atari.ale). The memory share of each process is MEM_FRACTION (default 0.9 / the
# games per GPU): lower it to leave room for other work on the same GPU.
set -u
out=$1; limit=$2; shift 2
games=(); while [ $# -gt 0 ] && [ "$1" != "--" ]; do games+=("$1"); shift; done
[ "${1:-}" = "--" ] && shift
[ ${#games[@]} -eq 0 ] && games=(breakout seaquest)
reserve=${EVAL_RESERVE:-240}
train=$(( limit - reserve )); [ "$train" -lt 60 ] && train=60
mkdir -p "$out/runs"
. "$(dirname "$0")/../lease.sh"
ensure_wheels || exit 1  # brax, mujoco-mjx, distrax, gymnax: from .whl/ or .whl-site/ (carry one)
if ! python -c "import gymnasium" 2>/dev/null; then  # gymnax's and ale-py's; .whl-site holds gymnax, not it
  python -m pip install --quiet --no-index --no-deps --find-links .whl-atari gymnasium==1.3.0 farama-notifications==0.0.6 \
    || { echo "gymnasium is missing: carry .whl-atari"; exit 1; }
fi
if ! python -c "import gymnax" 2>/dev/null; then
  python -m pip install --quiet --no-index --no-deps --find-links .whl --find-links .whl-atari gymnax==1.0.1 \
    seaborn==0.13.2 cloudpickle==3.1.2 || { echo "gymnax is missing: carry .whl (or .whl-site)"; exit 1; }
fi
if printf '%s\n' "${games[@]}" | grep -q '^ale-' && ! python -c "import ale_py" 2>/dev/null; then
  python -m pip install --quiet --no-index --no-deps --find-links .whl --find-links .whl-atari --find-links .whl-ale \
    ale-py==0.12.1 || { echo "ale-py is missing: carry .whl-ale (or .whl) holding its wheel"; exit 1; }
fi
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
