"""The consistency term's k-step chain as hand-written CUDA kernels (chain.cu), called through XLA's FFI (issue 21).

XLA runs the fused chain (`cdjax.consistency.fused_chain`) as some 340 small kernels per SGD minibatch, one after
another; these two kernels run the whole chain's forward, and the whole backward of its per-row cotangents, each in one
launch. The weight gradients stay XLA's products afterwards (`consistency._chain_weight_grads`).

The library is compiled with nvcc on first use, for the GPU at hand, into ~/.cache/cdjax/kernels (or
$CDJAX_KERNEL_CACHE), and registered with XLA as the FFI targets `cdjax_chain_fwd` and `cdjax_chain_bwd`. It is used
when $CDJAX_CHAIN_KERNEL is 1 and the chain's shapes fit (`usable`); anything else runs XLA's chain. nvcc is looked for
in $CUDA_HOME/bin, /usr/local/cuda/bin and $PATH.

Status (2026-11-27, one H100, `python -m benchmarks.chain_kernel`): the gradients match XLA's fused chain's (both
against the plain loop at the highest precision, and under vmap over seeds), but the value and gradient of the chain
takes 2.12 ms against XLA's 1.29 ms at the compare suite's 512 rows (1.93 against 1.30 ms at 10 seeds of 32 rows), so
the kernels stay off by default (benchmarks/results/2026-11-27-h100-chain-kernel/ says where their time goes).
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import os
import pathlib
import shutil
import subprocess

import jax
import jax.numpy as jnp
import numpy as np

from cdjax.protocol import ConfigError

SOURCE = pathlib.Path(__file__).with_name("chain.cu")
# "1": the kernels where they fit; "cluster": the cluster kernels (untested); unset or "0": XLA's chain
SWITCH_ENV = "CDJAX_CHAIN_KERNEL"
CACHE_ENV = "CDJAX_KERNEL_CACHE"  # where the compiled library goes (default ~/.cache/cdjax/kernels)
PROBE_ENV = "CDJAX_CHAIN_PROBE"  # timing probes of benchmarks.chain_kernel only: phases the forward skips (chain.cu)
SPLIT_COLS = 32  # the widest state the kernels take (kSplitCols)
SMEM_LIMIT = 220 * 1024  # bytes of shared memory a block may ask for (an H100's is 227 KB)


class KernelUnavailable(RuntimeError):
    """The kernels cannot be built or loaded here (no GPU, no nvcc, a compile error): the message says which."""


def _nvcc() -> str:
    for root in (os.environ.get("CUDA_HOME"), "/usr/local/cuda"):
        if root and (pathlib.Path(root) / "bin" / "nvcc").is_file():
            return str(pathlib.Path(root) / "bin" / "nvcc")
    found = shutil.which("nvcc")
    if not found:
        raise KernelUnavailable("nvcc not found ($CUDA_HOME/bin, /usr/local/cuda/bin, $PATH)")
    return found


def _arch() -> str:
    """sm_XY of the first GPU."""
    gpus = [d for d in jax.devices() if d.platform == "gpu"]
    if not gpus:
        raise KernelUnavailable("no GPU among jax.devices()")
    cc = getattr(gpus[0], "compute_capability", None)
    if not cc:
        raise KernelUnavailable(f"{gpus[0]} reports no compute capability")
    return "sm_" + str(cc).replace(".", "")


def build(verbose: bool = False) -> pathlib.Path:
    """The compiled library for this GPU, compiled now unless the cache holds it (keyed by the source, the
    architecture and jaxlib's FFI headers' version)."""
    arch = _arch()
    probe = int(os.environ.get(PROBE_ENV) or 0)
    tag = SOURCE.read_bytes() + arch.encode() + jax.__version__.encode() + str(probe).encode()
    key = hashlib.sha256(tag).hexdigest()[:16]
    cache = pathlib.Path(os.environ.get(CACHE_ENV) or pathlib.Path.home() / ".cache" / "cdjax" / "kernels")
    lib = cache / f"chain-{arch}-{key}.so"
    if lib.is_file():
        return lib
    cache.mkdir(parents=True, exist_ok=True)
    tmp = lib.with_suffix(f".{os.getpid()}.tmp")
    cmd = [_nvcc(), "-O3", "-std=c++17", "-shared", "-Xcompiler", "-fPIC", "-Xcompiler", "-w",
           "-diag-suppress", "940,2473", f"-gencode=arch=compute_{arch[3:]},code={arch}",
           f"-DCDJAX_CHAIN_PROBE={probe}", f"-I{jax.ffi.include_dir()}", str(SOURCE), "-o", str(tmp)]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        raise KernelUnavailable(f"nvcc failed ({done.returncode}): {done.stderr.strip()[-2000:]}")
    if verbose:
        print(" ".join(cmd), done.stderr, sep="\n")
    os.replace(tmp, lib)  # atomic: a concurrent build writes the same bytes
    return lib


@functools.cache
def load() -> ctypes.CDLL:
    """Build and load the library and register its two FFI targets with XLA (once per process)."""
    lib = ctypes.cdll.LoadLibrary(str(build()))
    for name, symbol in (("cdjax_chain_fwd", lib.CdjaxChainFwd), ("cdjax_chain_bwd", lib.CdjaxChainBwd),
                         ("cdjax_chain_fwd_cluster", lib.CdjaxChainFwdCluster),
                         ("cdjax_chain_bwd_cluster", lib.CdjaxChainBwdCluster)):
        jax.ffi.register_ffi_target(name, jax.ffi.pycapsule(symbol), platform="CUDA")
    return lib


def _register() -> None:
    """Build and register the kernels where a GPU is (the calls then run); elsewhere leave the calls unregistered, so
    that they trace and lower (shape checks on a CPU) but do not compile."""
    if jax.default_backend() == "gpu":
        load()


def block_smem(O: int, X: int, N1: int, H: int) -> int:
    """The larger shared memory (bytes) of the forward's and the backward's thread block (the cluster kernels' when
    they are switched on), as the library computes it."""
    f = load().CdjaxChainSmem
    f.restype, f.argtypes = ctypes.c_int64, [ctypes.c_int64] * 5
    return max(f(O, X, N1, H, 2), f(O, X, N1, H, 3)) if cluster_kernels() else max(f(O, X, N1, H, 0), f(O, X, N1, H, 1))


def switched_on() -> bool:
    """$CDJAX_CHAIN_KERNEL: "1" or "cluster" on, unset, empty or "0" off; ConfigError (one sentence) otherwise."""
    return _switch() in ("1", "cluster")


def cluster_kernels() -> bool:
    """Whether the forward and backward run as clusters of 4 blocks per 16 rows, each block holding a quarter of the
    weights in shared memory ($CDJAX_CHAIN_KERNEL=cluster; correct on an H100 on 2026-11-27 but slower than XLA's chain
    at one seed: benchmarks/results/2026-11-27-h100-chain-cluster/)."""
    return _switch() == "cluster"


def _switch() -> str:
    text = os.environ.get(SWITCH_ENV, "").strip()
    if text not in ("", "0", "1", "cluster"):
        raise ConfigError(f"${SWITCH_ENV} is {text!r}: set it to 1 (the CUDA chain kernels where they fit), cluster "
                          "(the kernels as clusters of blocks) or 0 (XLA's chain, the default)")
    return text


def usable(n_layers: int, O: int, X: int, N1: int, H: int, dtype) -> bool:
    """Whether the kernels take this chain: switched on, a GPU backend, a model of one hidden layer, float32, a
    state of at most SPLIT_COLS dimensions, blocks within shared memory, and the library built and loaded (a build
    failure says why once, then XLA's chain runs)."""
    if not switched_on() or jax.default_backend() != "gpu" or n_layers != 2 or dtype != jnp.float32 or O > SPLIT_COLS:
        return False
    if cluster_kernels() and H % 32:  # the cluster kernels split the GRU's units over 4 blocks in tiles of 8
        return False
    try:
        return block_smem(O, X, N1, H) <= SMEM_LIMIT
    except KernelUnavailable as err:
        _warn_once(str(err))
        return False


@functools.cache
def _warn_once(message: str) -> None:
    import warnings

    warnings.warn(f"cdjax: ${SWITCH_ENV}=1, but the chain kernels are unavailable, XLA's chain runs: {message}",
                  stacklevel=3)


def _shape(*dims) -> jax.ShapeDtypeStruct:
    return jax.ShapeDtypeStruct(tuple(int(d) for d in dims), jnp.float32)


def forward(clip: float, s0, z1a, gi_re, w_in, w_out, b_out, w_h, b_i, b_hn, stats):
    """The chain's forward (shapes in chain.cu) -> (u, states, xin, both_im, hh, hs)."""
    _register()
    (W, O), (k, _, N1), H, X = s0.shape, z1a.shape, w_h.shape[0], w_in.shape[0]
    out = (_shape(k, W, N1), _shape(k + 1, W, O), _shape(k + 1, W, X), _shape(k, W, 3 * H), _shape(k, 2 * W, 3 * H),
           _shape(k + 1, 2 * W, H))
    name = "cdjax_chain_fwd_cluster" if cluster_kernels() else "cdjax_chain_fwd"
    call = jax.ffi.ffi_call(name, out, vmap_method="broadcast_all")
    return call(s0, z1a, gi_re, w_in, w_out, b_out, w_h, b_i, b_hn, stats, clip=np.float32(clip))


def backward(clip: float, u, xin, both_im, hh, hs, gi_re, w_in, w_out, w_h, b_i, b_hn, stats, dh, ds):
    """The chain's backward of the per-row cotangents -> (dgi, dhh, dz, dz1, ds0) (shapes in chain.cu)."""
    _register()
    (W, O), (k, _, N1), H = ds.shape, u.shape, w_h.shape[0]
    out = (_shape(k, 2 * W, 3 * H), _shape(k, 2 * W, 3 * H), _shape(k, W, O), _shape(k, W, N1), _shape(W, O))
    name = "cdjax_chain_bwd_cluster" if cluster_kernels() else "cdjax_chain_bwd"
    call = jax.ffi.ffi_call(name, out, vmap_method="broadcast_all")
    return call(u, xin, both_im, hh, hs, gi_re, w_in, w_out, w_h, b_i, b_hn, stats, dh, ds, clip=np.float32(clip))
