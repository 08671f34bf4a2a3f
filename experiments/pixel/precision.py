"""Does a faster arrangement of the pixel model learn what float32 learns? Two sweeps of the same arms, seeds and
updates, one per arrangement (issue 22: "at equal updates, held-out ELBO, imitation error and log-likelihood match
float32's within their intervals"), compared metric by metric.

    python -m experiments.pixel.precision REFERENCE_RUN CANDIDATE_RUN [--labels float32 bfloat16/auto] [--out F.md]

Per arm and hyper-parameter label found in both run directories, each seed's score is its mean over the last WINDOW
logged updates up to the last update both sweeps reached (experiments.pixel.report.seed_scores), for
  heldout/elbo_per_frame, heldout/loglik_k, heldout/loglik_50, heldout/imitation, loss/imitation.
The table gives each sweep's IQM over seeds with a 95% bootstrap interval, and the per-seed difference (candidate
minus reference: the two sweeps share seeds, so the same seed starts from the same parameters and data) as a mean
with a 95% bootstrap interval. A metric "matches" when each IQM lies inside the other's interval; the difference's
interval says whether a shift is resolved at these seeds. Also each sweep's frames/s (training, all runs).
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib

import numpy as np

from cdjax import io
from cdjax.stats import bootstrap, iqm_interval, mean_columns
from experiments.pixel.report import WINDOW, _fmt, seed_scores, throughput

METRICS = (("heldout/elbo_per_frame", "held-out ELBO (nats/frame)"),
           ("heldout/loglik_k", "held-out log-lik at k"),
           ("heldout/loglik_50", "held-out log-lik at 50"),
           ("heldout/imitation", "held-out imitation MSE"),
           ("loss/imitation", "training imitation MSE"))


def _last(rows: list[dict]) -> int:
    """The last update every run of the sweep logged."""
    last: dict[tuple, int] = {}
    for r in rows:
        run = (r["arm"], r["hp"], r["seed"])
        last[run] = max(last.get(run, 0), r["update"])
    return min(last.values()) if last else 0


def _frames_per_update(run_dir: pathlib.Path) -> int | None:
    info = json.loads((run_dir / "run.json").read_text()) if (run_dir / "run.json").exists() else {}
    config = next((a["config"] for a in info.get("arms", [])), {})
    return config["batch_size"] * config["seq_len"] if config else None


def _mean_interval(values: list[float], reps: int) -> tuple[float, float, float]:
    if len(values) < 2:
        return (float(np.mean(values)) if values else math.nan), math.nan, math.nan
    est, interval = bootstrap(np.asarray(values, float)[:, None], lambda s: mean_columns(s[..., None]), reps, 0)
    return float(est[0]), float(interval[0, 0]), float(interval[1, 0])


def compare(reference: pathlib.Path, candidate: pathlib.Path, reps: int = 2000, window: int = WINDOW) -> dict:
    """{"update", "frames_per_s": (ref, cand), "rows": [{arm, metric, ref, cand, diff, matches, seeds}]}."""
    a, b = io.read_jsonl(reference / "metrics.jsonl"), io.read_jsonl(candidate / "metrics.jsonl")
    if not a or not b:
        raise SystemExit(f"no metrics in {reference if not a else candidate}")
    last = min(_last(a), _last(b))
    groups = sorted({(r["arm"], r["hp"]) for r in a} & {(r["arm"], r["hp"]) for r in b})
    rows = []
    for metric, label in METRICS:
        sa, sb = seed_scores(a, metric, last, window), seed_scores(b, metric, last, window)
        for arm, hp in groups:
            ka = {k[2]: v for k, v in sa.items() if k[:2] == (arm, hp) and math.isfinite(v)}
            kb = {k[2]: v for k, v in sb.items() if k[:2] == (arm, hp) and math.isfinite(v)}
            if not ka or not kb:
                continue
            ia, ib = iqm_interval(list(ka.values()), reps=reps), iqm_interval(list(kb.values()), reps=reps)
            shared = sorted(set(ka) & set(kb))
            diff = _mean_interval([kb[s] - ka[s] for s in shared], reps)
            matches = ia[1] <= ib[0] <= ia[2] and ib[1] <= ia[0] <= ib[2]
            rows.append({"arm": arm if hp == "default" else f"{arm} {hp}", "metric": metric, "label": label,
                         "reference": ia[:3], "candidate": ib[:3], "difference": diff, "matches": bool(matches),
                         "seeds": len(shared)})
    fpu_a, fpu_b = _frames_per_update(reference), _frames_per_update(candidate)
    speed = (throughput(a, fpu_a) if fpu_a else math.nan, throughput(b, fpu_b) if fpu_b else math.nan)
    return {"update": last, "window": window, "frames_per_s": speed, "rows": rows}


def markdown(result: dict, labels: tuple[str, str]) -> str:
    ref, cand = labels
    fa, fb = result["frames_per_s"]
    lines = [f"At update {result['update']} (each seed's mean over its last {result['window']} logged updates), "
             f"{ref} (reference) against {cand}; frames/s over all runs: {fa:,.0f} and {fb:,.0f}"
             + (f" ({fb / fa:.2f}x)" if fa and math.isfinite(fa) and math.isfinite(fb) else "") + ".", "",
             f"| arm | metric | {ref} | {cand} | {cand} - {ref} (per seed, mean) | seeds | match |",
             "| --- | --- | ---: | ---: | ---: | ---: | --- |"]
    for r in result["rows"]:
        lines.append(f"| {r['arm']} | {r['label']} | {_fmt(*r['reference'])} | {_fmt(*r['candidate'])} | "
                     f"{_fmt(*r['difference'])} | {r['seeds']} | {'yes' if r['matches'] else '**no**'} |")
    n = sum(r["matches"] for r in result["rows"])
    lines += ["", f"{n} of {len(result['rows'])} match (each IQM inside the other's 95% interval)."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(prog="python -m experiments.pixel.precision", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("reference", type=pathlib.Path, help="the float32 sweep's run directory")
    p.add_argument("candidate", type=pathlib.Path, help="the other arrangement's run directory")
    p.add_argument("--labels", nargs=2, default=("float32", "candidate"))
    p.add_argument("--window", type=int, default=WINDOW)
    p.add_argument("--reps", type=int, default=2000)
    p.add_argument("--out", default="", help="write the table here (markdown) and beside it the JSON")
    args = p.parse_args(argv)
    result = compare(args.reference, args.candidate, args.reps, args.window)
    text = markdown(result, tuple(args.labels))
    print(text, end="")
    if args.out:
        out = pathlib.Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text)
        out.with_suffix(".json").write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
