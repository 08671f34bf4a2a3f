"""The one place for runtime switches: XLA's flags, the compilation cache, the compile mode, NaN checks,
disabling jit.

`cdjax` adds its XLA flags when it is imported (`apply_xla_defaults`, before JAX starts its backends), and compiles
its own programs with per-program options (`compiler_options`: the compile mode's, the GPU's data-flow scheduling
of CUDA graphs, which the sweep runner drops for a program that would not fit in memory, and $CDJAX_XLA_OPTIONS).
Everything else goes through `configure`, which the CLI (--cache-dir, --compile-mode, --debug-nans,
--disable-jit), the tests, the benchmarks and the examples call:

    cdjax.runtime.configure(cache_dir=cdjax.runtime.default_cache_dir())

One switch lives beside the code it switches: $CDJAX_CHAIN_KERNEL=1 runs the consistency chain as hand-written CUDA
kernels where they fit (`cdjax.kernels.chain`, read when a chain is traced; off by default, slower than XLA's chain as
measured on 2026-11-27).
"""

from __future__ import annotations

import os
import pathlib
import warnings

# XLA:CPU's concurrency-optimised scheduler deadlocks some of cdjax's vmapped programs on a 2-core
# machine (seen with jax 0.10.2: 6 vmapped runs of the point-mass agent hang in BlockUntilReady every
# time, 2, 4 and 8 do not; with this flag, or pinned to one core, they run). It only affects the CPU backend.
CPU_SCHEDULER_FLAG = "--xla_cpu_enable_concurrency_optimized_scheduler=false"
# XLA:GPU's autotuner at level 1: it still times each GEMM and convolution candidate and keeps the fastest, but
# skips XLA's default (level 4) extras: filling the candidates' buffers with random data, refilling them between
# runs and comparing every candidate's result with a reference (which, at level 4, only logs a mismatch). One H200
# (2026-11-26, benchmarks/results/2026-11-26-h200-autotune/): the cold 4-arm ant sweep compiled in 68.7 s instead
# of 145.7 s (2026-11-25, level 4), while model-free, Mb-Mf and the paper's CD ran 0.98-0.999x the time per
# update of level 4 in the compare suite; one H100 in one lease (2026-11-26, benchmarks/results/2026-11-26-h100-levels/)
# 77.7 s against 87.2 s, the pixel update 1.0% slower. Only the GPU backend reads it. A user who names the level in XLA_FLAGS
# (e.g. --xla_gpu_autotune_level=4, XLA's own default) keeps theirs.
GPU_AUTOTUNE_FLAG = "--xla_gpu_autotune_level=1"
# XLA:GPU's cost model keeps the 2 best of its default Triton GEMM tilings (by its estimate) for the autotuner to
# time, not all of them (about 2,100 candidate kernels in the cold 4-arm ant sweep, whose compiling took about 660 of
# the 1,574 core-seconds on a 16-core host; benchmarks/results/2026-11-27-h100x4-compile-cores/). One H100 of a
# 16-core host, one lease (2026-11-27, benchmarks/results/2026-11-27-h100-gemm-tilings/): the cold 4-arm ant sweep
# started training after 65.4 s instead of 86.1 s, while Mb-Mf and the paper's CD ran 0.457 against 0.457 and 0.741
# against 0.740 s per update (the compare suite). cuBLAS stays among the candidates. A user who names the option in
# XLA_FLAGS keeps theirs: `--xla_gpu_experimental_cost_model_gemm_tiling_options=` (empty) is XLA's own search.
# An experimental XLA option: jax is pinned (pyproject.toml), and XLA aborts on an option it does not know, so a
# jax upgrade must keep it or drop it here.
GPU_GEMM_TILINGS_FLAG = "--xla_gpu_experimental_cost_model_gemm_tiling_options=top=2,top_from_default=1"
XLA_DEFAULTS = (CPU_SCHEDULER_FLAG, GPU_AUTOTUNE_FLAG, GPU_GEMM_TILINGS_FLAG)  # what `import cdjax` adds to XLA_FLAGS
# XLA:GPU's CUDA graphs (command buffers) scheduled by data flow, asked for per program (compiler_options), not in
# XLA_FLAGS: each kernel of a graph waits only on the kernels whose buffers it reads or overwrites, so independent ones
# run side by side (XLA's default, LHS, runs them in program order). cdjax's updates are chains of small kernels that
# leave most of the GPU idle, and many of them are independent: the policy's and the value network's passes, a layer's
# bias sum beside its weight product, the consistency term's model rollout beside its GRU passes. One H100, one lease
# (2026-11-27, benchmarks/results/2026-11-27-h100-concurrent/, then process-wide): per update model-free 0.359 against
# 0.408 s, Mb-Mf 0.410 against 0.453, the paper's CD 0.618 against 0.735, at 10 vmapped seeds Mb-Mf 0.342 and the
# paper's CD 0.529 (0.403 and 0.675 in program order). Per program, on another H100 (2026-11-27,
# benchmarks/results/2026-11-27-h100-per-program/): model-free 0.373, Mb-Mf 0.388, the paper's CD 0.618 s, and with
# XLA's deterministic ops and no autotuning the same arrays as program order, bit for bit. The price is memory:
# buffers are no longer reused between kernels that may run at once, so XLA's compiled footprint about doubles (1.44
# against 0.72 GiB for the paper's CD at 4096 envs), and the pixel presets' update of 30 runs no longer fits an H100 (it asked for 49.5 GiB at once;
# benchmarks/results/2026-11-27-h100-identity/). Hence per program, where cdjax can fall back: the sweep runner
# compiles a program again in program order when it would not fit beside the states (`compile_fitting`), and the
# process's other programs (Brax's, a user's own) keep XLA's scheduling. A user who names the option in XLA_FLAGS
# (--xla_gpu_command_buffer_scheduling_mode=LHS: XLA's own) keeps theirs for every program.
SCHEDULING_OPTION = "xla_gpu_command_buffer_scheduling_mode"
SCHEDULING = {SCHEDULING_OPTION: "CONCURRENT"}
CACHE_ENV = "CDJAX_JAX_CACHE"  # environment variable naming the persistent compilation cache
MODE_ENV = "CDJAX_COMPILE_MODE"  # environment variable naming the compile mode (configure's compile_mode wins)
# More XLA options for cdjax's own programs only, on top of the compile mode's: NAME=VALUE words, as XLA_FLAGS writes
# them (`CDJAX_XLA_OPTIONS="--xla_gpu_copy_insertion_use_region_analysis=true"`). Unlike XLA_FLAGS they leave the
# process's other programs (Brax's, a user's own) as they are, so one process can set a flag for cdjax against a
# baseline without it; they are part of the persistent cache's key and of a benchmark's recorded compiler options.
OPTIONS_ENV = "CDJAX_XLA_OPTIONS"

# What cdjax asks of XLA with every program it compiles itself (a sweep's reset, init, phase and chunk programs):
# per-program compiler options, so a notebook can change mode between cells, and part of the persistent cache's key.
COMPILE_MODES: dict[str, dict] = {
    "default": {},  # XLA's own settings
    # Triton's GEMM fusions off (GPU): cuBLAS alone, far fewer kernels for the autotuner to try. One H200
    # (2026-11-25, benchmarks/results/2026-11-25-h200-compile-{flags,speed}/): the cold 4-arm ant sweep started
    # training after 77.4 s (process-wide flag) or 109.1 s (this per-program option) instead of 145.7 s, but every
    # update then runs 1.05-1.19x longer (1.19x: the paper's CD schedule), so it is not the default: it is for
    # notebook iteration and short checks. No effect on a CPU.
    "fast": {"xla_gpu_enable_triton_gemm": False},
    # For a GPU run that another process can repeat bit for bit (a CPU's already is): XLA's deterministic
    # implementations of the ops that otherwise sum with atomics (scatter-adds, in the physics among others), and no
    # autotuning, whose choice of GEMM kernel depends on timings. On one H100 (2026-11-27,
    # benchmarks/results/2026-11-27-h100-identity/) two processes at XLA's settings differed in about half the arrays of
    # the ant's state after 3 updates; with these two settings in XLA_FLAGS, model-free, Mb-Mf and the paper's CD gave
    # identical arrays (benchmarks/results/2026-11-27-h100-per-program/). The price: 1.71-1.87x the time per update
    # there. Its own two-process check, with init compiled in the mode too, gave identical arrays for model-free and
    # the paper's CD; XLA's deterministic ops alone cost about 1.86x (2026-11-27, H100,
    # benchmarks/results/2026-11-27-h100-determinism/). No effect on a CPU.
    "deterministic": {"xla_gpu_deterministic_ops": True, "xla_gpu_autotune_level": 0},
    # XLA's own autotuning for cdjax's programs: its default level (4) and its full search of Triton GEMM tilings, in
    # place of the two flags `import cdjax` adds for compile time (GPU_AUTOTUNE_FLAG, GPU_GEMM_TILINGS_FLAG). For long
    # sweeps, where a compile is paid once and every update is faster. One H100 (2026-11-27,
    # benchmarks/results/2026-11-27-h100-tuned/): at 10 vmapped seeds of 256 envs the paper's CD ran 0.528 against
    # 0.586 s per update (Mb-Mf 0.326 against 0.331), its program compiling 38 against 28 s; the cold 4-arm ant sweep
    # started training after 97 s (76 s at the defaults, on another host). The gain is the tiling search's: the cost
    # model's top two miss the batched GEMMs of the vmapped chain. At 4096 envs and one seed the arms ran within the
    # spread between processes (benchmarks/results/2026-11-27-h100-outer/). No effect on a CPU.
    "tuned": {"xla_gpu_autotune_level": 4, "xla_gpu_experimental_cost_model_gemm_tiling_options": ""},
}
_mode: str | None = None  # set by configure; None: $CDJAX_COMPILE_MODE, else "default"


def _named(option: str, flags: str) -> bool:
    """Whether XLA_FLAGS text `flags` sets `option` (a name without dashes)."""
    return any(word.lstrip("-").split("=")[0] == option for word in flags.split())


def apply_xla_defaults() -> None:
    """Add cdjax's XLA flags (XLA_DEFAULTS: CPU_SCHEDULER_FLAG, GPU_AUTOTUNE_FLAG, GPU_GEMM_TILINGS_FLAG) to XLA_FLAGS,
    each unless the user set that option already. XLA reads XLA_FLAGS when a backend starts: `import cdjax` calls this
    first thing, and warns when a JAX backend had started before, so that the flags it adds cannot apply in
    this process."""
    flags = os.environ.get("XLA_FLAGS", "")
    added = []
    for flag in XLA_DEFAULTS:
        if not _named(flag.split("=")[0].lstrip("-"), flags):
            flags = f"{flags} {flag}".strip()
            added.append(flag)
    os.environ["XLA_FLAGS"] = flags
    if added and _backends_started():
        warnings.warn(f"A JAX backend started before cdjax was imported, so the XLA flags cdjax adds ({' '.join(added)}) "
                      "do not apply in this process (XLA reads XLA_FLAGS when a backend starts): import cdjax before "
                      "anything that calls JAX, or put them in XLA_FLAGS yourself.", RuntimeWarning, stacklevel=3)


def _backends_started() -> bool:
    """Whether this process has started a JAX backend (False when JAX is not imported yet, or cannot say)."""
    import sys

    if "jax" not in sys.modules:
        return False
    try:
        from jax._src import xla_bridge

        return bool(xla_bridge.backends_are_initialized())
    except Exception:  # noqa: BLE001 - a JAX without this private function: say nothing rather than guess
        return False


def default_cache_dir() -> str:
    """$CDJAX_JAX_CACHE, else ~/.cache/cdjax/jax."""
    return os.environ.get(CACHE_ENV, str(pathlib.Path.home() / ".cache" / "cdjax" / "jax"))


def check_cache_dir(cache_dir: str | os.PathLike, source: str = "the compilation cache") -> None:
    """Make the cache directory; ConfigError (one sentence naming where it came from: --cache-dir, $CDJAX_JAX_CACHE)
    when it is a file, cannot be made, or cannot be written."""
    from cdjax.protocol import ConfigError

    path = pathlib.Path(cache_dir)
    try:
        str(path).encode("utf-8")
        if path.exists() and not path.is_dir():
            raise ConfigError(f"{source} {path} is a file, not a directory; name a directory for JAX's compilation "
                              "cache.")
        os.makedirs(path, exist_ok=True)
        if not os.access(path, os.W_OK | os.X_OK):
            raise ConfigError(f"{source} {path} cannot be written ({os.strerror(13)}); name a directory you can "
                              "write for JAX's compilation cache.")
    except UnicodeEncodeError:
        raise ConfigError(f"{source} {ascii(str(path))} is not UTF-8 text; name another directory.") from None
    except OSError as err:
        raise ConfigError(f"{source} {path} cannot be used ({err.strerror or err}); name a directory you can write "
                          "for JAX's compilation cache.") from None


def check_compile_mode(mode: str, source: str = "compile_mode") -> str:
    """`mode` when it names a COMPILE_MODES entry, else ConfigError (one sentence naming `source`)."""
    from cdjax.protocol import ConfigError

    if mode not in COMPILE_MODES:
        raise ConfigError(f"{source} must be one of {', '.join(COMPILE_MODES)}, got {mode!r}.")
    return mode


def environment_compile_mode() -> str:
    """$CDJAX_COMPILE_MODE's mode (ConfigError when it names none), else "default"."""
    text = os.environ.get(MODE_ENV, "").strip()
    return check_compile_mode(text, f"${MODE_ENV}") if text else "default"


def compile_mode() -> str:
    """The compile mode in force: configure's, else environment_compile_mode()."""
    return _mode if _mode is not None else environment_compile_mode()


def compiler_options(mode: str | None = None, *, in_order: bool = False) -> dict:
    """The XLA options cdjax compiles its programs with, for `jax.stages.Lowered.compile` or `jax.jit(...,
    compiler_options=...)`: those of `mode` (COMPILE_MODES; default: the compile mode in force) and, unless `in_order`
    or XLA_FLAGS names the option, the GPU kernels of each CUDA graph scheduled by data flow (SCHEDULING; no effect on
    a CPU)."""
    options = dict(COMPILE_MODES[compile_mode() if mode is None else check_compile_mode(mode)])
    if not in_order and not _named(SCHEDULING_OPTION, os.environ.get("XLA_FLAGS", "")):
        options.update(SCHEDULING)
    options.update(environment_options())
    return options


def environment_options() -> dict:
    """$CDJAX_XLA_OPTIONS (OPTIONS_ENV) as compiler options: NAME=VALUE words separated by spaces, as in XLA_FLAGS
    (a leading -- allowed; a value may hold commas and '='), true and false as booleans, whole numbers as ints, anything else as text. ConfigError, one
    sentence, for a word that is not NAME=VALUE, for the scheduling option (set it in XLA_FLAGS, where the runner's
    in-order fallback keeps to it), and for an option XLA does not take (checked once per text by compiling a
    one-line program: call it after `configure`, since JAX settles at a process's first compile whether the
    persistent cache is used)."""
    text = os.environ.get(OPTIONS_ENV, "").strip()
    if not text:
        return {}
    if text not in _CHECKED_OPTIONS:
        _CHECKED_OPTIONS[text] = _check_options(text)
    return dict(_CHECKED_OPTIONS[text])


_CHECKED_OPTIONS: dict[str, dict] = {}


def _parse_value(value: str):
    if value.lower() in ("true", "false"):
        return value.lower() == "true"
    if value.lstrip("-").isdigit():
        return int(value)
    return value


def _check_options(text: str) -> dict:
    from cdjax.protocol import ConfigError

    options = {}
    for word in text.split():
        name, eq, value = word.lstrip("-").partition("=")
        if not name or not eq:
            raise ConfigError(f"${OPTIONS_ENV} takes NAME=VALUE words (as XLA_FLAGS writes them), got {word!r}.")
        if name == SCHEDULING_OPTION:
            raise ConfigError(f"${OPTIONS_ENV} cannot set {SCHEDULING_OPTION}: put --{name}={value} in XLA_FLAGS, "
                              "where the sweep runner's fallback for programs that would not fit keeps to it.")
        options[name] = _parse_value(value)
    import jax
    import jax.numpy as jnp

    try:
        jax.jit(lambda x: x + 1).lower(jnp.zeros(1)).compile(options)
    except Exception as err:  # noqa: BLE001 - XLA's refusal (an unknown name, a value of the wrong type), in its words
        reason = str(err).splitlines()[0].removeprefix("INVALID_ARGUMENT: ").rstrip(".")
        raise ConfigError(f"${OPTIONS_ENV}={text!r}: XLA refuses it ({reason}).") from None
    return options


def concurrent(options: dict) -> bool:
    """Whether compiler options `options` ask for cdjax's data-flow scheduling (SCHEDULING)."""
    return all(options.get(k) == v for k, v in SCHEDULING.items())


def configure(*, cache_dir: str | os.PathLike | None = None, debug_nans: bool = False, disable_jit: bool = False,
              min_compile_time_s: float = 0.5, cache_source: str = "the compilation cache",
              compile_mode: str | None = None) -> None:
    """Persistent compilation cache (programs compiling longer than `min_compile_time_s` are kept; ConfigError when
    `cache_dir` cannot be used, naming `cache_source`), NaN checks on every operation, jit off (for debugging), the
    compile mode of the programs compiled from now on (COMPILE_MODES; None leaves it as it is); and no Brax
    deprecation notice on every run."""
    import jax

    global _mode
    if compile_mode is not None:
        _mode = check_compile_mode(compile_mode)

    warnings.filterwarnings("ignore", message="Brax System", category=UserWarning)
    if cache_dir:
        check_cache_dir(cache_dir, cache_source)
        jax.config.update("jax_compilation_cache_dir", str(cache_dir))
        jax.config.update("jax_persistent_cache_min_compile_time_secs", min_compile_time_s)
    jax.config.update("jax_debug_nans", debug_nans)
    jax.config.update("jax_disable_jit", disable_jit)
