"""The package's layout as its imports draw it: a folder per setting under cdjax/agents/, a shared layer below
them that imports no setting, and a host side that reaches settings only by name through the registry."""

import ast
import pathlib

import cdjax

ROOT = pathlib.Path(cdjax.__file__).resolve().parent
SETTINGS = sorted(p.name for p in (ROOT / "agents").iterdir() if (p / "__init__.py").is_file())
SHARED = ("checks", "consistency", "envs", "kernels", "normalize", "numerics", "optim", "protocol", "replay", "runtime",
          "selfpredictive")
FACE = "cdjax"  # cdjax/__init__.py re-exports the observation-space agent's public names


def _module(path: pathlib.Path) -> str:
    parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: pathlib.Path) -> set[str]:
    """Every cdjax module a file imports, at its top or inside a function (`from cdjax import x` counts as
    cdjax.x: it may be a module)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
            found |= {f"{node.module}.{alias.name}" for alias in node.names}
    return {name for name in found if name == "cdjax" or name.startswith("cdjax.")}


def _setting_of(module: str) -> str | None:
    parts = module.split(".")
    return parts[2] if len(parts) > 2 and parts[1] == "agents" and parts[2] in SETTINGS else None


MODULES = {_module(p): _imports(p) for p in ROOT.rglob("*.py")}


def test_the_settings_are_packages_alike():
    assert SETTINGS == ["atari", "obs", "offpolicy", "pixel"]
    for name in SETTINGS:
        assert (ROOT / "agents" / name / "config.py").is_file(), name  # each setting's Config and HParams
    for old in ("config", "train", "losses", "networks", "rollout", "mpc", "presets", "mbmf"):
        assert not (ROOT / f"{old}.py").exists() and not (ROOT / old).is_dir(), old  # the obs agent is in agents/obs


def test_no_setting_imports_another_setting():
    for module, imported in MODULES.items():
        own = _setting_of(module)
        if own is None:
            continue
        others = {name for name in imported if _setting_of(name) not in (None, own)}
        assert not others, f"{module} imports another setting: {sorted(others)}"


def test_the_shared_layer_imports_no_setting_nor_the_host_side():
    shared = [m for m in MODULES if m.split(".")[1:2] and m.split(".")[1] in SHARED]
    assert {m.split(".")[1] for m in shared} == set(SHARED)
    for module in shared:
        below = {name for name in MODULES[module] if name.split(".")[1:2] and name.split(".")[1] not in SHARED}
        assert not below, f"{module} (shared) imports {sorted(below)}"


def test_the_host_side_reaches_settings_only_through_the_registry():
    host = [m for m in MODULES if m != FACE and not m.startswith("cdjax.agents") and m.split(".")[1] not in SHARED]
    assert {"cdjax.cli", "cdjax.sweep", "cdjax.runner.loop", "cdjax.io", "cdjax.plots"} <= set(host)
    for module in host:
        direct = {name for name in MODULES[module] if _setting_of(name) is not None}
        assert not direct, f"{module} (host side) imports a setting's package: {sorted(direct)}"
