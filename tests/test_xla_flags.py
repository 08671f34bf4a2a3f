"""benchmarks.xla_flags: the XLA flags compiled into jaxlib's and its plugins' libraries (GPU units ask it before
passing a flag that an image's XLA may refuse at start-up)."""

from __future__ import annotations

from benchmarks import xla_flags


def test_flags_are_the_names_in_jaxlibs_and_the_plugins_libraries_only(tmp_path):
    (tmp_path / "jaxlib").mkdir()
    (tmp_path / "jax_plugins" / "cuda").mkdir(parents=True)
    (tmp_path / "other").mkdir()
    (tmp_path / "jaxlib" / "_jax.so").write_bytes(b"\x00xla_gpu_b_flag\x00junk xla_gpu_a=1 xla_cpu_c\x00xla_gpu_b_flag")
    (tmp_path / "jax_plugins" / "cuda" / "plugin.so").write_bytes(b"--xla_gpu_d_2\xff")
    (tmp_path / "jaxlib" / "notes.txt").write_bytes(b"xla_gpu_not_a_library")
    (tmp_path / "other" / "x.so").write_bytes(b"xla_gpu_elsewhere")
    assert xla_flags.known_flags(site=tmp_path) == ["xla_gpu_a", "xla_gpu_b_flag", "xla_gpu_d_2"]
    assert xla_flags.known_flags("xla_cpu_", site=tmp_path) == ["xla_cpu_c"]


def test_this_jaxlib_knows_its_own_flags():
    names = xla_flags.known_flags()
    assert "xla_gpu_autotune_level" in names and "xla_gpu_enable_triton_gemm" in names
    assert names == sorted(set(names))


def test_accepts_starts_xla_with_the_flag_and_tells_a_listed_name_xla_refuses():
    """A name in the libraries need not be a flag: XLA aborts at start-up on one it does not know, which `accepts`
    sees in a child process (CPU: the xla_gpu_ flags are parsed on every backend)."""
    import pytest

    assert xla_flags.accepts("xla_gpu_autotune_level=0")
    assert not xla_flags.accepts("xla_gpu_no_such_flag_here=1")
    assert xla_flags.main(["--accepts", "xla_gpu_autotune_level=0"]) == ["xla_gpu_autotune_level=0"]
    with pytest.raises(SystemExit) as stop:
        xla_flags.main(["--accepts", "xla_gpu_autotune_level=0", "xla_gpu_no_such_flag_here=1"])
    assert stop.value.code == 1
