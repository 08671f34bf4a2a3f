"""experiments.pixel.precision: two sweeps' held-out metrics compared seed by seed at the last update both reached."""

import json

import numpy as np
import pytest

from experiments.pixel import precision


def _sweep(path, last, value_of, seeds=6):
    """A run directory of the ltq arm: every metric of METRICS at updates 1..last, value_of(metric, seed, update)."""
    path.mkdir(parents=True)
    rows = [{"arm": "ltq", "hp": "default", "seed": s, "update": u, "wall_s": float(u),
             **{m: value_of(m, s, u) for m, _ in precision.METRICS}}
            for s in range(seeds) for u in range(1, last + 1)]
    (path / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    (path / "run.json").write_text(json.dumps({"arms": [{"config": {"batch_size": 2, "seq_len": 5}}]}))
    return path


def test_precision_compares_at_the_common_update_and_finds_a_shift_only_where_there_is_one(tmp_path):
    spread = np.linspace(-1.0, 1.0, 6)  # per seed

    def reference(metric, seed, update):
        return 10.0 + spread[seed] + 0.001 * update

    def candidate(metric, seed, update):  # runs longer; after update 20 it is a different model altogether
        if update > 20:
            return 1e6
        shift = 5.0 if metric == "heldout/imitation" else 0.0
        return reference(metric, seed, update) + shift

    ref = _sweep(tmp_path / "f32", 20, reference)
    cand = _sweep(tmp_path / "bf16", 30, candidate)
    result = precision.compare(ref, cand, reps=300, window=5)
    assert result["update"] == 20
    rows = {r["metric"]: r for r in result["rows"]}
    assert set(rows) == {m for m, _ in precision.METRICS}
    for metric, row in rows.items():
        assert row["seeds"] == 6
        point, low, high = row["difference"]
        if metric == "heldout/imitation":
            assert point == pytest.approx(5.0) and low == pytest.approx(5.0) and not row["matches"]
        else:
            assert point == pytest.approx(0.0, abs=1e-9) and row["matches"]
    # the frames/s of each sweep: 10 frames per update per run, 6 runs, wall_s = the update
    assert result["frames_per_s"][0] == pytest.approx(6 * 10 * 20 / 20)
    text = precision.markdown(result, ("float32", "bfloat16/auto"))
    assert "4 of 5 match" in text and "**no**" in text


def test_every_pixel_preset_builds_a_valid_config_and_grid():
    """The task presets run the arrangement the precision check validated (bfloat16, per-run convolutions) with the
    fused core (the same function as flax, faster on a GPU: experiments/pixel/data/core-h200/); each
    preset's config must pass PixelConfig's own checks (e.g. the transposed upsampling runs only in float32) and
    each grid value the hyper-parameters' ranges, or a sweep of it would stop at its first line."""
    import itertools

    from cdjax.agents.pixel import PRESETS, SETTING, PixelConfig

    for name, preset in PRESETS.items():
        config = PixelConfig(**preset.config)
        for field, values in preset.hparams.items():
            for value in values:
                SETTING.check_hparam(field, value)
        for combo in itertools.product(*preset.hparams.values()):
            SETTING.hparams_type(**dict(zip(preset.hparams, combo)))
        if name != "pixel-tiny":
            assert (config.compute_dtype, config.conv_impl, config.core_impl, config.output_grad) == (
                "bfloat16", "per-run", "fused", "compute"), name
