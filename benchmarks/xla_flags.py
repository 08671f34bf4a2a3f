"""Which XLA flags this environment's XLA takes. XLA refuses an unknown flag in XLA_FLAGS at start-up (jax 0.11.2
no longer knew --xla_gpu_enable_split_k_autotuning) and has no flag that lists them, so a GPU unit asks this first.

    python -m benchmarks.xla_flags [--prefix xla_gpu_]      # the candidates: names compiled into the libraries
    python -m benchmarks.xla_flags --accepts NAME=VALUE ... # which of these XLA takes (exit 1 if any is refused)

The names found in jaxlib's and its CUDA plugin's libraries are candidates only: a name can be there without being a
flag (jax 0.11.2's libraries hold xla_gpu_experimental_enable_split_k_rewrite, which its XLA_FLAGS parser refuses),
so a unit that passes a flag asks `--accepts`, which starts XLA in a child process with the flag set.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import re
import subprocess
import sys


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


def accepts(setting: str) -> bool:
    """Whether XLA starts with XLA_FLAGS=--SETTING (NAME=VALUE; XLA aborts the process on a flag it does not know):
    a child Python process with that environment creates JAX's default backend."""
    env = {**os.environ, "XLA_FLAGS": f"--{setting.lstrip('-')}"}
    probe = "import jax; jax.devices()"
    return subprocess.run([sys.executable, "-c", probe], env=env, stdout=subprocess.DEVNULL,
                          stderr=subprocess.DEVNULL).returncode == 0


def main(argv=None) -> list[str]:
    p = argparse.ArgumentParser(prog="python -m benchmarks.xla_flags", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--prefix", default="xla_gpu_")
    p.add_argument("--accepts", nargs="+", metavar="NAME=VALUE",
                   help="print those of these settings XLA takes; exit status 1 if it refuses any")
    args = p.parse_args(argv)
    if args.accepts:
        taken = [s for s in args.accepts if accepts(s)]
        print("\n".join(taken))
        if len(taken) < len(args.accepts):
            raise SystemExit(1)
        return taken
    names = known_flags(args.prefix)
    print("\n".join(names))
    return names


if __name__ == "__main__":
    main()
