"""The summary of a run: per arm and hyper-parameter, IQM and 95% intervals of the final value, the area under the
curve and the evaluation return (`summary_rows`), as summary.md and summary.csv."""

from __future__ import annotations

import csv
import math
import pathlib
from typing import Sequence

import numpy as np

from cdjax import stats
from cdjax.plots.curves import Curves, Names, per_seed_auc, per_seed_final, per_seed_skipped

_STATS = (("final", per_seed_final), ("auc", per_seed_auc))


def summary_rows(curves: dict[tuple[str, str], Curves], evals: dict | None = None, reps: int = 2000,
                 seed: int = 0, names: Names = Names()) -> list[dict]:
    """One row per (arm, hp), sorted by final return IQM (best first, NaN last).

    Columns: arm, hp, arm_type, seeds (those with a finite final return, the figure the rows are ranked by),
    logged_seeds, left_out_seed_ids (logged seeds without one), updates, env_steps, then for each of final/auc x
    return/discounted_return: <stat>_<target>_iqm, _ci_low, _ci_high, _seeds (the seeds finite in it); and with
    evals, for each evaluation mode (det, stoch) found: eval_<mode>_return_* and eval_<mode>_discounted_return_*
    (the same four: _seeds counts the seeds whose latest evaluation is finite in it) and eval_<mode>_seeds (those of
    the evaluation return).
    """
    evals = evals or {}
    modes = sorted({det for (_, _, det) in evals}, reverse=True)  # deterministic first
    rows = []
    for (arm, hp), c in curves.items():
        ranked = np.isfinite(per_seed_final(c, names.ret))  # as every statistic, the seeds column counts finite ones
        row = {"arm": arm, "hp": hp, "arm_type": c.arm_type or "", "seeds": int(ranked.sum()),
               "logged_seeds": int(len(c.seeds)), "left_out_seed_ids": " ".join(str(s) for s in c.seeds[~ranked]),
               "updates": int(c.present.any(axis=0).sum()),
               "env_steps": float(np.nanmax(c.env_steps)) if np.isfinite(c.env_steps).any() else math.nan}
        for stat, fn in _STATS:
            for target, name in (("return", names.ret), ("discounted_return", names.discounted_ret)):
                iqm, lo, hi, n = stats.iqm_interval(fn(c, name), reps, seed)
                row.update({f"{stat}_{target}_iqm": iqm, f"{stat}_{target}_ci_low": lo,
                            f"{stat}_{target}_ci_high": hi, f"{stat}_{target}_seeds": n})
        skipped = per_seed_skipped(c, names.skipped)
        row["nonfinite_seeds"] = int((skipped > 0).sum())
        row["skipped_steps"] = int(np.nansum(skipped))
        row["nonfinite_seed_ids"] = " ".join(str(s) for s in c.seeds[skipped > 0])
        for det in modes:
            mode = "det" if det else "stoch"
            ev = evals.get((arm, hp, det))
            for target in ("return", "discounted_return"):
                iqm, lo, hi, n = stats.iqm_interval(ev[target] if ev else [], reps, seed)
                row.update({f"eval_{mode}_{target}_iqm": iqm, f"eval_{mode}_{target}_ci_low": lo,
                            f"eval_{mode}_{target}_ci_high": hi, f"eval_{mode}_{target}_seeds": n})
            row[f"eval_{mode}_seeds"] = int(np.isfinite(ev["return"]).sum()) if ev else 0
        rows.append(row)
    rows.sort(key=lambda r: (not np.isfinite(r["final_return_iqm"]), -np.nan_to_num(r["final_return_iqm"])))
    return rows


def _fmt(x: float) -> str:
    return "n/a" if not np.isfinite(x) else f"{x:.4g}"


def _other_count(row: dict, prefix: str) -> int | None:
    """The seeds behind the row's figure `prefix` where they are not as many as the seeds column's (a seed not
    evaluated, a non-finite evaluation, a figure finite for other seeds than the final return); None where they are,
    or where there is no figure."""
    n = row.get(f"{prefix}_seeds", row["seeds"])
    return n if n and n != row["seeds"] else None


def _label(row: dict) -> str:
    """A summary row's arm and hyper-parameter label, as its notes name it ("cd alpha=1.0", or "cd" alone)."""
    return " ".join(part for part in (row["arm"], row["hp"]) if part)


def _cell(row: dict, prefix: str) -> str:
    iqm, lo, hi = row[f"{prefix}_iqm"], row[f"{prefix}_ci_low"], row[f"{prefix}_ci_high"]
    if not np.isfinite(iqm):
        return "n/a"
    text = _fmt(iqm) if not np.isfinite(lo) else f"{_fmt(iqm)} [{_fmt(lo)}, {_fmt(hi)}]"
    n = _other_count(row, prefix)
    return text if n is None else f"{text} (**n = {n}**)"


def _seeds_cell(row: dict) -> str:
    """The seeds behind the row's figures, "4 of 5" where logged seeds were left out."""
    n, logged = row["seeds"], row["logged_seeds"]
    return str(n) if n == logged else f"**{n} of {logged}**"


def summary_markdown(rows: list[dict], title: str = "", notes: Sequence[str] = ()) -> str:
    """The summary table of `rows` (summary_rows') with its notes; `notes`: more paragraphs under it (the sweep's
    note on the measure the arms are ranked by, `cdjax.runner.plan.return_note`)."""
    columns = [("final return", "final_return"), ("AUC return", "auc_return"),
               ("final disc. return", "final_discounted_return"), ("AUC disc. return", "auc_discounted_return")]
    for mode, words in (("det", "deterministic"), ("stoch", "stochastic")):
        if rows and f"eval_{mode}_return_iqm" in rows[0]:
            columns += [(f"eval return ({words})", f"eval_{mode}_return"),
                        (f"eval disc. return ({words})", f"eval_{mode}_discounted_return")]
    flagged = [row for row in rows if row.get("nonfinite_seeds")]
    short = [row for row in rows if row["seeds"] < row["logged_seeds"]]
    counted = [(row, name, n) for row in rows for name, prefix in columns
               if (n := _other_count(row, prefix)) is not None]
    head = ["rank", "arm", "hp", "seeds", "env steps"] + [name for name, _ in columns] + (
        ["non-finite"] if flagged else [])
    lines = [f"# {title}" if title else "# Summary", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for i, row in enumerate(rows, 1):
        steps = f"{row['env_steps']:.3g}" if np.isfinite(row["env_steps"]) else "n/a"
        arm = row["arm"] + (f" ({row['arm_type']})" if row["arm_type"] and row["arm_type"] != row["arm"] else "")
        cells = [str(i), arm, row["hp"] or "-", _seeds_cell(row), steps] + [_cell(row, p) for _, p in columns]
        if flagged:
            cells.append(f"**{row['nonfinite_seeds']} of {row['logged_seeds']} seeds**"
                         if row.get("nonfinite_seeds") else "-")
        lines.append("| " + " | ".join(cells) + " |")
    lines += [
        "",
        "IQM across seeds with a 95% stratified-bootstrap confidence interval "
        f"({'rliable' if stats.rly is not None else 'rliable method, computed locally: rliable.library does not import'}). "
        "With fewer than 4 seeds "
        "the IQM equals the mean; with 1 seed no interval is given. Final: mean of the last "
        f"{stats.FINAL_FRACTION:.0%} of each seed's logged updates. AUC: mean of each seed's whole return curve, "
        "each point weighted by the env steps since the previous one (an Mb-Mf phase's point by the phase's "
        "steps; points before the first finished episode are skipped). Eval: mean return over the evaluation "
        "episodes of each seed's latest evaluation.",
    ]
    if short:
        runs = "; ".join(f"{_label(row)} seeds {row['left_out_seed_ids']}" for row in short)
        lines += ["", "**Seeds left out**: the seeds column counts the seeds with a finite final return (the figure "
                      "the rows are ranked by), and every figure uses only the seeds finite in it; these logged "
                      f"seeds have no finite return over the last {stats.FINAL_FRACTION:.0%} of their logged "
                      f"updates: {runs}."]
    if counted:
        figures = "; ".join(f"{_label(row)} {name}: n = {n} (seeds column {row['seeds']})" for row, name, n in counted)
        lines += ["", "**Seed counts**: a figure marked n = N is over N seeds, not the seeds column's: an evaluation "
                      "column counts the seeds whose latest evaluation is finite in it (a seed not evaluated, or "
                      f"evaluated to a non-finite return, is not in it), every other column the seeds finite in it: "
                      f"{figures}."]
    if flagged:
        runs = "; ".join(f"{_label(row)} seeds {row['nonfinite_seed_ids']}: {row['skipped_steps']} steps"
                         for row in flagged)
        lines += ["", f"**Non-finite training**: these runs skipped optimiser steps whose loss or gradient was not "
                      f"finite (the parameters stayed as they were; their numbers are suspect): {runs}."]
    for note in notes:
        lines += ["", note]
    return "\n".join(lines) + "\n"


def _write_csv(path: pathlib.Path, rows: list[dict], columns: Sequence[str] | None = None) -> pathlib.Path:
    columns = list(columns or (rows[0].keys() if rows else []))
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns)
        writer.writeheader()
        for row in rows:
            writer.writerow({k: ("" if isinstance(v, float) and not np.isfinite(v) else v) for k, v in row.items()})
    return path
