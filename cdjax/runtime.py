"""The one place for runtime switches: XLA's flags, the compilation cache, the compile mode, NaN checks,
disabling jit, and the versions a result record names.

Importing cdjax changes nothing in the process. cdjax's XLA flags (`XLA_DEFAULTS`) are applied by its entry points
(the `cdjax` command, `cdjax.runner.run_sweep`, the benchmarks) and by a notebook that opts in, first thing, before
anything starts a JAX backend:

    import cdjax
    cdjax.runtime.apply_xla_defaults()

cdjax compiles its own programs with per-program options (`compiler_options`: the compile mode's, the GPU's data-flow
scheduling of CUDA graphs, which the sweep runner drops for a program that would not fit in memory, and
$CDJAX_XLA_OPTIONS). Everything else goes through `configure`, which the CLI (--cache-dir, --compile-mode,
--debug-nans, --disable-jit), the tests, the benchmarks and the examples call:

    cdjax.runtime.configure(cache_dir=cdjax.runtime.default_cache_dir())

What each flag and mode was measured to do on GPUs is on the docs site's speed page (docs/speed.md).
"""

from __future__ import annotations

import os
import pathlib
import re
import sys
import warnings

# XLA:CPU's concurrency-optimised scheduler deadlocks some of cdjax's vmapped programs on a 2-core machine (several
# vmapped runs of the point-mass agent hang in BlockUntilReady; with this flag, or pinned to one core, they run).
# Only the CPU backend reads it.
CPU_SCHEDULER_FLAG = "--xla_cpu_enable_concurrency_optimized_scheduler=false"
# XLA:GPU's autotuner at level 1: it still times each GEMM and convolution candidate and keeps the fastest, but skips
# the extras of XLA's default level 4 (random-filled buffers, refills between runs, comparing every candidate with a
# reference), which about halve a cold sweep's compile time at no measured cost per update (docs/speed.md). Only the
# GPU backend reads it. A user who names the level in XLA_FLAGS keeps theirs.
GPU_AUTOTUNE_FLAG = "--xla_gpu_autotune_level=1"
# XLA:GPU's cost model keeps the 2 best of its default Triton GEMM tilings (by its estimate) for the autotuner to
# time, not all of them: thousands fewer candidate kernels in a cold sweep, so it starts training sooner, at the same
# time per update (docs/speed.md). cuBLAS stays among the candidates. A user who names the option in XLA_FLAGS keeps
# theirs: `--xla_gpu_experimental_cost_model_gemm_tiling_options=` (empty) is XLA's own search. An experimental XLA
# option, and XLA aborts on an option it does not know: a JAX outside the tested range must keep it or drop it here.
GPU_GEMM_TILINGS_FLAG = "--xla_gpu_experimental_cost_model_gemm_tiling_options=top=2,top_from_default=1"
XLA_DEFAULTS = (CPU_SCHEDULER_FLAG, GPU_AUTOTUNE_FLAG, GPU_GEMM_TILINGS_FLAG)  # what apply_xla_defaults adds
# XLA:GPU's CUDA graphs (command buffers) scheduled by data flow, asked for per program (compiler_options), not in
# XLA_FLAGS: each kernel of a graph waits only on the kernels whose buffers it reads or overwrites, so independent ones
# run side by side (XLA's default, LHS, runs them in program order). cdjax's updates are chains of small kernels that
# leave most of the GPU idle, and many are independent (the policy's and the value network's passes, the consistency
# term's model rollout beside its GRU passes), so updates run faster (docs/speed.md). The price is memory: buffers are
# no longer reused between kernels that may run at once, so XLA's compiled footprint about doubles. Hence per program,
# where cdjax can fall back: the sweep runner compiles a program again in program order when it would not fit beside
# the states (`compile_fitting`), and the process's other programs (Brax's, a user's own) keep XLA's scheduling. A user
# who names the option in XLA_FLAGS (--xla_gpu_command_buffer_scheduling_mode=LHS: XLA's own) keeps theirs.
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
    # Triton's GEMM fusions off (GPU): cuBLAS alone, far fewer kernels for the autotuner to try, so a cold sweep
    # compiles sooner, but every update runs longer: for notebook iteration and short checks. No effect on a CPU.
    "fast": {"xla_gpu_enable_triton_gemm": False},
    # For a GPU run that another process can repeat bit for bit (a CPU's already is): XLA's deterministic
    # implementations of the ops that otherwise sum with atomics (scatter-adds, in the physics among others), and no
    # autotuning, whose choice of GEMM kernel depends on timings. The price is a slower update (docs/speed.md).
    # No effect on a CPU.
    "deterministic": {"xla_gpu_deterministic_ops": True, "xla_gpu_autotune_level": 0},
    # XLA's own autotuning for cdjax's programs: its default level (4) and its full search of Triton GEMM tilings, in
    # place of the two compile-time flags of XLA_DEFAULTS (GPU_AUTOTUNE_FLAG, GPU_GEMM_TILINGS_FLAG). For long sweeps,
    # where a compile is paid once and every update is faster: the cost model's top two tilings miss the batched GEMMs
    # of the vmapped chain (docs/speed.md). No effect on a CPU.
    "tuned": {"xla_gpu_autotune_level": 4, "xla_gpu_experimental_cost_model_gemm_tiling_options": ""},
}
_mode: str | None = None  # set by configure; None: $CDJAX_COMPILE_MODE, else "default"


def _named(option: str, flags: str) -> bool:
    """Whether XLA_FLAGS text `flags` sets `option` (a name without dashes)."""
    return any(word.lstrip("-").split("=")[0] == option for word in flags.split())


def apply_xla_defaults() -> None:
    """Add cdjax's XLA flags (XLA_DEFAULTS: CPU_SCHEDULER_FLAG, GPU_AUTOTUNE_FLAG, GPU_GEMM_TILINGS_FLAG) to XLA_FLAGS,
    each unless the user set that option already. XLA reads XLA_FLAGS when a backend starts: the `cdjax` command,
    `run_sweep` and the benchmarks call this first thing, a notebook calls it in its first cell; it warns when a JAX
    backend had started before, so that the flags it adds cannot apply in this process."""
    flags = os.environ.get("XLA_FLAGS", "")
    if flags.strip() and not flags.strip().startswith("-"):  # the name of a file holding the flags: left as it is
        return
    added = []
    for flag in XLA_DEFAULTS:
        if not _named(flag.split("=")[0].lstrip("-"), flags):
            flags = f"{flags} {flag}".strip()
            added.append(flag)
    os.environ["XLA_FLAGS"] = flags
    if added and _backends_started():
        warnings.warn(f"A JAX backend started before cdjax.runtime.apply_xla_defaults() was called, so the XLA flags cdjax adds ({' '.join(added)}) "
                      "do not apply in this process (XLA reads XLA_FLAGS when a backend starts): call it before "
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


VERSIONED = ("jax", "jaxlib", "brax", "mujoco", "mujoco-mjx")  # the packages a result record names, beside cdjax


def installed(name: str) -> str | None:
    """The installed version of distribution `name` (None when it is not installed), without importing it."""
    from importlib import metadata

    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


def versions(backend: bool = True) -> dict:
    """The versions a result record names: cdjax's, and those of jax, jaxlib, brax, mujoco and mujoco-mjx as installed
    (None for one that is not), read from the installed distributions' metadata, so nothing is imported; with
    `backend`, JAX's default backend too ("cpu", "gpu", "tpu"), which starts one."""
    package = sys.modules[__name__.partition(".")[0]]  # cdjax itself, loaded before any of its modules

    record = {"cdjax": package.__version__, **{name: installed(name) for name in VERSIONED}}
    if backend:
        import jax

        record["backend"] = jax.default_backend()
    return record


# XLA aborts the whole process (a fatal log line, exit 134) on an XLA_FLAGS entry it does not know, when a backend
# starts; `check_xla_flags` has a forked copy of the process parse them first (constructing compile options parses
# XLA_FLAGS and starts no backend) and turns XLA's last words into one sentence.
def _xla_flags_rejected() -> str | None:
    """What XLA says of XLA_FLAGS when it rejects them, else None (also where this system cannot fork)."""
    if not hasattr(os, "fork"):
        return None
    from jax._src.lib import _jax  # noqa: F401  (imported here, so that the child does not import it again)

    read, write = os.pipe()
    sys.stderr.flush()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # fork with threads (JAX warns of it): the child only parses and exits
        pid = os.fork()
    if pid == 0:  # the child: its stderr into the pipe, XLA parses the flags, and it ends without Python's shutdown
        try:
            os.close(read)
            os.dup2(write, 2)
            _jax.CompileOptions()
        finally:
            os._exit(0)
    os.close(write)
    with os.fdopen(read, "rb") as pipe:
        said = pipe.read().decode("utf-8", "replace")
    _, status = os.waitpid(pid, 0)
    if os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0:
        return None
    logged = [line for line in said.splitlines() if re.match(r"[EF]\d{4} ", line)]  # glog's error and fatal lines
    logged.sort(key=lambda line: line[0] != "E")  # an error line names the entry; the fatal one only says it failed
    return logged[0].split("] ", 1)[-1].strip()[:300] if logged else f"it ended the process (status {status})"


def check_xla_flags() -> None:
    """ConfigError, one sentence naming the variable, the value and what it takes, for an XLA_FLAGS that would end
    the process when JAX's backend starts (an entry XLA does not know, a file name that cannot be read) or that
    leaves the CPU backend no device (--xla_force_host_platform_device_count below 1). Nothing to do once a backend
    has started (XLA has read the flags then)."""
    from cdjax.protocol import ConfigError

    flags = os.environ.get("XLA_FLAGS", "").strip()
    if not flags or _backends_started():
        return
    for word in flags.split():
        name, _, value = word.partition("=")
        if name == "--xla_force_host_platform_device_count" and not (value.isdigit() and int(value) >= 1):
            raise ConfigError(f"XLA_FLAGS sets {word}, which leaves the CPU backend no device: it takes a whole "
                              "number of CPU devices, at least 1 (e.g. --xla_force_host_platform_device_count=1).")
    rejected = _xla_flags_rejected()
    if rejected is not None:
        flags = " ".join(word for word in flags.split() if word not in XLA_DEFAULTS)  # the user's words
        raise ConfigError(f"XLA_FLAGS={flags!r} is refused by XLA ({rejected}); it takes --NAME=VALUE words naming "
                          "XLA's own flags (or the name of a file holding them): correct or remove that entry.")


def _platforms_here() -> list[str]:
    """The backends JAX could start here, in words: the CPU's, and those whose plugins are installed."""
    import importlib.util

    from jax._src import xla_bridge

    found = ["cpu"] + [name for name in ("cuda", "rocm") if name in xla_bridge._backend_factories]
    if importlib.util.find_spec("libtpu") is not None:
        found.append("tpu")
    return found


def check_backend() -> None:
    """Start JAX's backend (what the command would do at its first array); ConfigError, one sentence naming
    JAX_PLATFORMS, its value and the backends JAX could start here, when it cannot start."""
    import jax

    from cdjax.protocol import ConfigError

    try:
        jax.devices()
    except RuntimeError as err:
        asked = os.environ.get("JAX_PLATFORMS") or jax.config.jax_platforms or ""
        why = str(err).splitlines()[0].split(" (set JAX_PLATFORMS")[0][:300] if str(err) else type(err).__name__
        available = ", ".join(_platforms_here())
        if asked:
            raise ConfigError(f"JAX_PLATFORMS={asked} names a backend JAX cannot start on this machine ({why}); the "
                              f"backends it can start here: {available} (e.g. JAX_PLATFORMS=cpu, or unset it)."
                              ) from None
        raise ConfigError(f"JAX could not start a backend ({why}); the backends it can start here: {available} "
                          "(JAX_PLATFORMS names one).") from None
