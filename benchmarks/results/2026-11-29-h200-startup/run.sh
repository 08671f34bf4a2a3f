#!/usr/bin/env bash
# Issue 71's GPU unit, for one 25-minute H200 loan: every part writes under OUT, a part starts only if its estimate
# fits in what is left of SECONDS (default 1320: 22 minutes), and each runs under `timeout` of what is left.
#   setsid bash benchmarks/results/2026-11-29-h200-startup/run.sh OUT [SECONDS] > OUT.log 2>&1 < /dev/null &
#   TINY=1 RUNS=1 PYTHON=... bash benchmarks/results/2026-11-29-h200-startup/run.sh OUT 3600   # CPU rehearsal, tiny sizes
# Parts, in order (what is left out when time runs short is the last ones; OUT/progress says what ran and what not):
#   sweep-after-cold    3 whole `cdjax sweep --env ant --arms model-free mbmf cd-k5 cd` processes at the presets
#                       (3 seeds, 1M env steps per run), this checkout, each with its own empty compilation cache
#   learning-*          benchmarks.learning, one seed, cdjax then Brax PPO, humanoid then ant (Brax's settings:
#                       learning.TASKS), one whole process each, timed here; each its own empty cache
#   sweep-before-cold   the 4-arm sweep as above with the code of d1792b3 (OLD_CODE, or exported here by git)
#   sweep-after-warm, sweep-before-warm   the same with the compilation cache their cold run-0 filled
# PARTS="name ..." runs only those parts (a second loan: what the first left out; a warm part without its cold part's
# cache fills one first). Estimates (H200, from the kept figures): sweep-after-cold 3 x ~110 s, the learning pairs
# ~370 s (humanoid: cdjax ~140, Brax ~230) and ~270 s (ant), sweep-before-cold 3 x ~140 s, the warm parts 3 x ~45 and
# 3 x ~70 s: about 29 minutes in all, so one 22-minute unit is expected to leave out the warm parts and perhaps the
# last before-cold process (OUT/progress names them) for a second loan.
# Then OUT/versus.md: cdjax's whole process, and its compile + training, over Brax's whole process, per task, and when
# cdjax's evaluation return first reached Brax's final one (seconds after its launch, and of training).
set -u
out=$(realpath -m "${1:?output directory}")
budget=${2:-1320}
cd "$(dirname "$0")/../../.."  # the repository root
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
py=${PYTHON:-python}
runs=${RUNS:-3}  # processes per sweep part (the rehearsal: RUNS=1)
mkdir -p "$out"
start=$(date +%s)
left() { echo $(( budget - $(date +%s) + start )); }
say() { echo "$(date -u +%T) $*" | tee -a "$out/progress"; }
if [ -n "${TINY:-}" ]; then  # estimates in seconds on a 2-core CPU (cold), for the skip rule only
  size=(--tiny); tasks=(point); est_sweep=200; est_warm=60; est_cdjax=120; est_brax=120
else  # estimates from the kept H200 figures (docs/speed.md, 2026-11-29-h200-sweep-smoke, issue 71's harness runs)
  size=(--env ant); tasks=(humanoid ant); est_sweep=140; est_warm=50; est_cdjax=130; est_brax=240
  sweep_args=(-- --arms model-free mbmf cd-k5 cd --seeds 3)
fi
# the code before issue 71's changes: OLD_CODE (e.g. carried to the device: `git archive d1792b3 cdjax | tar -x -C DIR`
# here, DIR git-ignored), or exported from this checkout's git history where it has one
old=${OLD_CODE:-$out/code-d1792b3}
if [ ! -d "$old/cdjax" ]; then
  mkdir -p "$old" && git archive d1792b3 cdjax 2> /dev/null | tar -x -C "$old" 2> /dev/null
  [ -d "$old/cdjax" ] || say "no $old/cdjax (no OLD_CODE, no git history): the before parts will be skipped"
fi
say "start: $(left) s for the unit; $($py -c 'import jax; print(jax.__version__, jax.devices())' 2>&1 | tail -1)"

wanted() { [ -z "${PARTS:-}" ] || [[ " $PARTS " == *" $1 "* ]] || { say "not in PARTS: $1"; return 1; }; }

sweep() {  # name code runs estimate-per-process [--cache-dir DIR]
  local name=$1 code=$2 runs=$3 est=$4; shift 4
  if [ "$(left)" -lt "$est" ]; then say "skipped $name: $(left) s left, one process takes about $est s"; return; fi
  wanted "$name" || return 0
  if [ ! -d "$code/cdjax" ]; then say "skipped $name: no $code/cdjax"; return; fi
  if [ "${1:-}" = --cache-dir ] && [ ! -d "$2" ]; then set -- --cache warm; fi  # no cold run here: one fills it first
  say "$name"
  timeout "$(left)" "$py" -m benchmarks.startup "${size[@]}" --runs "$runs" --code "$code" --time-limit "$(left)" \
    --out "$out/$name" "$@" ${sweep_args[@]+"${sweep_args[@]}"} > "$out/$name.log" 2>&1
  say "$name: status $?"
}

learning() {  # task framework estimate
  local name=learning-$1-$2
  wanted "$name" || return 0
  if [ "$(left)" -lt "$3" ]; then say "skipped $name: $(left) s left, it takes about $3 s"; return; fi
  say "$name"
  local t0 t1 rc tiny=()
  [ -n "${TINY:-}" ] && tiny=(--tiny)
  t0=$(date +%s.%N)
  timeout "$(left)" "$py" -m benchmarks.learning --tasks "$1" --frameworks "$2" --seeds 1 "${tiny[@]}" \
    --cache-dir "$out/$name-cache" --out "$out/$name" > "$out/$name.log" 2>&1
  rc=$?; t1=$(date +%s.%N)
  echo "{\"task\": \"$1\", \"framework\": \"$2\", \"launched\": $t0, \"ended\": $t1, \"status\": $rc}" >> "$out/processes.jsonl"
  say "$name: status $rc, $(awk "BEGIN {print $t1 - $t0}") s"
}

sweep sweep-after-cold "$PWD" "$runs" "$est_sweep"
for task in "${tasks[@]}"; do
  learning "$task" cdjax "$est_cdjax"
  learning "$task" brax "$est_brax"
done
sweep sweep-before-cold "$old" "$runs" "$est_sweep"
sweep sweep-after-warm "$PWD" "$runs" "$est_warm" --cache-dir "$out/sweep-after-cold/cache-0"
sweep sweep-before-warm "$old" "$runs" "$est_warm" --cache-dir "$out/sweep-before-cold/cache-0"

"$py" - "$out" > "$out/versus.md" <<'EOF'
import json, pathlib, sys
out = pathlib.Path(sys.argv[1])
procs = [json.loads(l) for l in (out / "processes.jsonl").read_text().splitlines()] if (out / "processes.jsonl").exists() else []
print("| task | cdjax whole s | Brax whole s | cdjax / Brax | cdjax compile + train s | (compile + train) / Brax | "
      "Brax final return | cdjax reached it: s after launch (of training) |\n|---|---:|---:|---:|---:|---:|---:|---:|")
for task in dict.fromkeys(p["task"] for p in procs):
    p = {q["framework"]: q for q in procs if q["task"] == task and q["status"] == 0}
    rows = {f: [json.loads(l) for l in (out / f"learning-{task}-{f}" / "rows.jsonl").read_text().splitlines()]
            for f in p if (out / f"learning-{task}-{f}" / "rows.jsonl").exists()}
    if set(rows) != {"cdjax", "brax"}:
        print(f"| {task} | {' and '.join(sorted(set(['cdjax', 'brax']) - set(rows)))} did not finish |"); continue
    whole = {f: p[f]["ended"] - p[f]["launched"] for f in p}
    last, target = rows["cdjax"][-1], max(rows["brax"], key=lambda r: r["env_steps"])["eval_return"]
    reached = next((r for r in rows["cdjax"] if r["eval_return"] >= target), None)
    when = f"{reached['at'] - p['cdjax']['launched']:.1f} ({reached['train_s']:.1f})" if reached else "not reached"
    ct = last["compile_s"] + last["train_s"]
    print(f"| {task} | {whole['cdjax']:.1f} | {whole['brax']:.1f} | {whole['cdjax'] / whole['brax']:.2f} | {ct:.1f} | "
          f"{ct / whole['brax']:.2f} | {target:.1f} | {when} |")
EOF
say "done: $(left) s left"
