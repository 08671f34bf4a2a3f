"""Committed figures re-encoded as 256-colour palette PNGs, so that the tree still travels to a GPU machine.

    python -m experiments.compact_pngs [PATH ...]      # default: every PNG git tracks

What travels with a device call (the tracked tree and the carried wheels) may not exceed 64 MiB (`carry_size` in
experiments/wheels.sh counts it), and PNGs were a good part of the tree. Matplotlib writes full-colour RGBA; a plot
has a few hundred colours, most of them anti-aliased edges. Each opaque PNG is quantised to 256 colours (median cut,
no dithering) and rewritten when that is smaller: to the eye the same figure, about half the bytes (what it saved
and moved when it ran: docs/development.md).
A PNG with any transparency is left as it is (its background would change), and so is one already in a palette.
The data behind every figure stays where it is; this changes only how the picture is stored.
"""

from __future__ import annotations

import argparse
import io
import pathlib
import subprocess

from PIL import Image


def compact(raw: bytes) -> bytes | None:
    """The PNG `raw` as a 256-colour palette PNG, or None when it is not smaller or must stay as it is."""
    image = Image.open(io.BytesIO(raw))
    if image.mode == "P" or "transparency" in image.info:
        return None
    if image.mode in ("RGBA", "LA") and image.getchannel("A").getextrema()[0] < 255:
        return None
    palette = image.convert("RGB").quantize(colors=256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
    out = io.BytesIO()
    palette.save(out, "PNG", optimize=True)
    return out.getvalue() if out.tell() < len(raw) else None


def main(argv=None) -> None:
    p = argparse.ArgumentParser(prog="python -m experiments.compact_pngs", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("paths", nargs="*", help="PNG files (default: every *.png git tracks)")
    args = p.parse_args(argv)
    paths = args.paths or subprocess.run(["git", "ls-files", "*.png"], capture_output=True, text=True,
                                         check=True).stdout.split()
    before = after = 0
    for name in paths:
        path = pathlib.Path(name)
        raw = path.read_bytes()
        new = compact(raw)
        if new is not None:
            path.write_bytes(new)
        before, after = before + len(raw), after + len(new if new is not None else raw)
    print(f"{len(paths)} PNGs: {before:,} -> {after:,} bytes")


if __name__ == "__main__":
    main()
