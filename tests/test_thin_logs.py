"""experiments.thin_logs: the copies the GPU scripts bring back keep what the reports read."""

from __future__ import annotations

import json

from cdjax import io
from experiments.pixel.report import throughput
from experiments.thin_logs import thin_dir, thin_rows


def _rows(updates: int, runs: list[tuple]) -> list[dict]:
    return [{"arm": arm, "hp": "default", "seed": seed, "update": u, "wall_s": 0.5 * u, "x": u * 10 + seed}
            for u in range(1, updates + 1) for arm, seed in runs]


def test_every_run_keeps_its_tail_whole_its_ends_and_about_the_points_asked():
    runs = [("a", 0), ("a", 1), ("b", 0)]
    rows = _rows(1000, runs)
    kept = thin_rows(rows, points=100, tail=20)
    for arm, seed in runs:
        mine = [r["update"] for r in kept if (r["arm"], r["seed"]) == (arm, seed)]
        assert mine == sorted(mine)  # original order
        assert mine[0] == 1 and mine[-20:] == list(range(981, 1001))
        assert 90 <= len(mine) <= 110, len(mine)
    assert all(r in rows for r in kept)  # rows are copied, never altered


def test_a_short_log_is_kept_whole(tmp_path):
    rows = _rows(30, [("a", 0), ("a", 1)])
    assert thin_rows(rows, points=250, tail=60) == rows
    run = tmp_path / "src" / "task" / "pixel"
    (run / "checkpoints").mkdir(parents=True)
    (run / "run.json").write_text("{}")
    (run / "eval.jsonl").write_text('{"arm": "a"}\n')
    (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in _rows(500, [("a", 0), ("b", 0)])))
    (out,) = thin_dir(tmp_path / "src", tmp_path / "dest", points=50, tail=10)
    assert out == tmp_path / "dest" / "task" / "pixel"
    assert sorted(p.name for p in out.iterdir()) == ["eval.jsonl", "metrics.jsonl.xz", "run.json"]
    thinned = list(io.read_jsonl(out / "metrics.jsonl"))  # the compressed copy, read in place of the missing file
    full = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert len(thinned) < len(full) / 4
    # the pixel report's throughput reads each run's last update and the wall clock: the same from either copy
    assert throughput(thinned, 800) == throughput(full, 800) == 2 * 500 * 800 / 250.0


def test_compact_strips_keep_the_first_sequence_and_steps_as_a_palette_png(tmp_path):
    import numpy as np
    from PIL import Image

    from experiments.pixel.report import compact_strips

    cell, steps, rows = 6, 9, 3 * 2  # two sequences of three rows, 9 steps of 4x4 frames in 1-pixel frames
    image = np.random.default_rng(0).integers(0, 255, (rows * cell, steps * cell, 3), dtype=np.uint8)
    (tmp_path / "src").mkdir()
    Image.fromarray(image).save(tmp_path / "src" / "ltq.png")
    (out,) = compact_strips(str(tmp_path / "src"), str(tmp_path / "dest"), steps=4, sequences=1, cell=cell)
    small = Image.open(out)
    assert out.name == "ltq.png" and small.mode == "P" and small.size == (4 * cell, 3 * cell)
    # the palette keeps the picture: mean colour error well under the 0-255 range's spread
    error = np.abs(np.asarray(small.convert("RGB"), np.float32) - image[:3 * cell, :4 * cell]).mean()
    assert error < 8, error


def test_learning_curves_take_the_updates_every_seed_logged():
    from experiments.pixel.report import curve

    rows = [{"arm": "ltq", "hp": "default", "seed": s, "update": u, "m": float(u * (s + 1))}
            for u in range(1, 32) for s in range(3) if not (s == 2 and u == 21)]
    (label, (updates, values)), = curve(rows, (("m", "metric"),), every=10, reps=50).items()
    assert label == "ltq" and updates == [1, 11, 31]  # 21 lacks seed 2
    assert [round(v[0], 6) for v in values["m"]] == [2.0, 22.0, 62.0]  # the IQM of 1x, 2x, 3x: the middle seed


def test_the_final_window_is_the_same_on_a_thinned_log_as_on_the_whole_one():
    """stats.final_values with steps averages the last 10% of the env steps: a log thinned unevenly (sparse early,
    whole at the end, as thin_rows keeps it) gives the figure of the whole log; counting points would not."""
    import numpy as np

    from cdjax import stats

    rows = _rows(1000, [("a", 0)])
    for r in rows:
        r["x"] = float(r["update"])  # a rising curve: the window's extent decides the mean
    kept = thin_rows(rows, points=100, tail=150)
    steps_all = np.array([r["update"] for r in rows], float)
    steps_kept = np.array([r["update"] for r in kept], float)
    full, thinned = np.array([[r["x"] for r in rows]]), np.array([[r["x"] for r in kept]])
    whole = stats.final_values(full, np.ones_like(full, bool), steps=steps_all)[0]
    assert whole == np.mean(np.arange(901, 1001))  # updates 901..1000: the last 10% of the steps
    assert stats.final_values(thinned, np.ones_like(thinned, bool), steps=steps_kept)[0] == whole
    by_points = stats.final_values(thinned, np.ones_like(thinned, bool))[0]
    assert by_points > whole + 20  # the last 10% of ~240 kept points: only the last ~24 updates
    assert stats.final_values(full, np.ones_like(full, bool))[0] == whole  # a whole log: both windows agree


def test_compact_pngs_keeps_the_picture_in_fewer_bytes_and_leaves_transparency_alone():
    """A plot-like opaque RGBA image (flat colours, an anti-aliased line) comes back as a smaller palette PNG of the
    same size whose pixels are within a few levels of the original; an image with transparent pixels, and a palette
    image, come back as None (left as they are)."""
    import io as bytes_io

    import numpy as np
    from PIL import Image

    from experiments.compact_pngs import compact

    y, x = np.mgrid[0:120, 0:400]
    rgba = np.full((120, 400, 4), 255, np.uint8)
    for i, color in enumerate([(31, 119, 180), (255, 127, 14), (44, 160, 44)]):
        near = np.clip(1.5 - np.abs(y - (30 + 30 * i + 10 * np.sin(x / (20 + 5 * i)))), 0, 1)[..., None]
        rgba[..., :3] = (rgba[..., :3] * (1 - near) + np.array(color) * near).astype(np.uint8)

    def png(array, mode="RGBA"):
        out = bytes_io.BytesIO()
        Image.fromarray(array, mode).save(out, "PNG")
        return out.getvalue()

    raw = png(rgba)
    new = compact(raw)
    assert new is not None and len(new) < len(raw)
    image = Image.open(bytes_io.BytesIO(new))
    assert image.mode == "P" and image.size == (400, 120)
    assert np.abs(np.asarray(image.convert("RGB"), int) - rgba[..., :3].astype(int)).max() <= 16
    see_through = rgba.copy()
    see_through[:10, :10, 3] = 0
    assert compact(png(see_through)) is None
    assert compact(new) is None
