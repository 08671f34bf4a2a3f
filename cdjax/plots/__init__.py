"""Plots and summary tables of a run directory (pandas-free; matplotlib without pyplot).

    curves = load_metrics(run_dir)        # {(arm, hp_label): Curves with arrays [seeds, updates]}
    paths = plot_run(run_dir)             # PNGs + the CSV behind each, summary.md, summary.csv
    paths = plot_runs([run_a, run_b], out)  # the same of several runs' seeds pooled (runs of other --seed)

The statistics (IQM across seeds with 95% stratified-bootstrap intervals, final value, area under the
curve) are cdjax.stats'. Which metric is the return, the discounted return and the diagnostics panels is
read from run.json (the setting's names), with the observation-space setting's names for logs without one.
Missing values (null in metrics.jsonl, e.g. the return before the first finished episode) are NaN here.

Rooms: `curves` (the logs read into per-seed arrays), `summary` (the tables), `figures` (the PNGs and their CSVs).
"""


from cdjax.plots.curves import (DISC_RETURN, MODEL_PANELS, RETURN, ROW_KEYS, SKIPPED, Curves, Names, load_eval,
                                load_metrics, per_seed_auc, per_seed_final, per_seed_skipped, pool_curves,
                                pool_seed_arrays)
from cdjax.plots.figures import plot_run, plot_runs
from cdjax.plots.summary import summary_markdown, summary_rows

__all__ = ["DISC_RETURN", "MODEL_PANELS", "RETURN", "ROW_KEYS", "SKIPPED", "Curves", "Names", "load_eval", "load_metrics",
           "per_seed_auc", "per_seed_final", "per_seed_skipped", "plot_run", "plot_runs", "pool_curves",
           "pool_seed_arrays", "summary_markdown", "summary_rows"]
