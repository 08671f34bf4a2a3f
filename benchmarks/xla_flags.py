"""The XLA GPU flags this environment's jaxlib (and its CUDA plugin) knows, one per line: the names compiled into
their shared libraries. XLA refuses an unknown flag in XLA_FLAGS at start-up (jax 0.11.2 no longer knew
--xla_gpu_enable_split_k_autotuning), and XLA has no flag that lists them, so a GPU unit asks this first.

    python -m benchmarks.xla_flags [--prefix xla_gpu_]
"""

from __future__ import annotations

import argparse
import pathlib
import re


def known_flags(prefix: str = "xla_gpu_", site: pathlib.Path | None = None) -> list[str]:
    """Sorted names starting with `prefix` found in the .so files under site's (default: jaxlib's site-packages)
    jaxlib and jax_plugins."""
    if site is None:
        import jaxlib

        site = pathlib.Path(jaxlib.__file__).resolve().parent.parent
    pattern = re.compile(re.escape(prefix).encode() + rb"[a-z0-9_]+")
    names = set()
    for top in ("jaxlib", "jax_plugins"):
        for lib in (site / top).rglob("*.so"):
            names.update(m.decode() for m in pattern.findall(lib.read_bytes()))
    return sorted(names)


def main(argv=None) -> list[str]:
    p = argparse.ArgumentParser(prog="python -m benchmarks.xla_flags", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--prefix", default="xla_gpu_")
    names = known_flags(p.parse_args(argv).prefix)
    print("\n".join(names))
    return names


if __name__ == "__main__":
    main()
