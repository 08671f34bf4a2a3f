"""The package's layout as its imports draw it: three layers, bottom to top, and no import running back up.

1. the shared layer (`SHARED`): errors, numerics, the consistency term, envs, the protocol ... imports no setting
   and nothing of the host side;
2. the settings: a folder per setting under cdjax/agents/, each importing the shared layer and the registry
   (`cdjax.agents`), never another setting nor the host side;
3. the host side (`HOST`: io, multihost, runner, evaluate, plots, cli ...), which reaches a setting only by name
   through the registry.

`cdjax` itself (its __init__, the face) re-exports from every layer, lazily. Imports inside functions count as
imports at the top do. No circle, between modules or between packages, and no file over `MAX_LINES` lines."""

import ast
import pathlib

import cdjax

ROOT = pathlib.Path(cdjax.__file__).resolve().parent
SETTINGS = sorted(p.name for p in (ROOT / "agents").iterdir() if (p / "__init__.py").is_file())
# The layer table (cdjax's top-level names; a package counts with everything under it).
SHARED = ("errors", "runtime", "numerics", "normalize", "optim", "replay", "checks", "protocol", "consistency",
          "envs", "options")
REGISTRY = "cdjax.agents"  # the settings' registry: in the settings' layer, below every setting
HOST = ("io", "multihost", "sweep", "evaluate", "stats", "plots", "runner", "cli", "budget", "__main__")
FACE = "cdjax"  # cdjax/__init__.py re-exports the public names of every layer
MAX_LINES = 500


def _module(path: pathlib.Path) -> str:
    parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: pathlib.Path) -> set[str]:
    """Every cdjax module a file imports, at its top or inside a function: `from P import x` counts as P.x where
    that is a module of cdjax, else as P (x is a name P defines: P's code runs)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found |= {f"{node.module}.{a.name}" if f"{node.module}.{a.name}" in NAMES else node.module
                      for a in node.names}
    return {name for name in found if name == "cdjax" or name.startswith("cdjax.")}


def _setting_of(module: str) -> str | None:
    parts = module.split(".")
    return parts[2] if len(parts) > 2 and parts[1] == "agents" and parts[2] in SETTINGS else None


NAMES = {_module(p) for p in ROOT.rglob("*.py")}
MODULES = {_module(p): _imports(p) for p in ROOT.rglob("*.py")}


def test_the_settings_are_packages_alike():
    assert {"atari", "obs", "pixel"} <= set(SETTINGS)  # the paper's three, and any setting added beside them
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
    assert {m.split(".")[1] for m in shared} <= set(SHARED)
    for module in shared:
        below = {name for name in MODULES[module] if name.split(".")[1:2] and name.split(".")[1] not in SHARED}
        assert not below, f"{module} (shared) imports {sorted(below)}"


def test_the_host_side_reaches_settings_only_through_the_registry():
    host = [m for m in MODULES if m != FACE and not m.startswith("cdjax.agents") and m.split(".")[1] not in SHARED]
    assert {"cdjax.cli", "cdjax.sweep", "cdjax.runner.loop", "cdjax.io", "cdjax.plots"} <= set(host)
    for module in host:
        direct = {name for name in MODULES[module] if _setting_of(name) is not None}
        assert not direct, f"{module} (host side) imports a setting's package: {sorted(direct)}"


def _layer(module: str) -> int | None:
    """1 shared, 2 the settings and their registry, 3 the host side, 4 the face; None for a module the table does
    not place (test_every_module_is_in_the_layer_table names it)."""
    if module == FACE:
        return 4
    top = module.split(".")[1]
    if top in SHARED:
        return 1
    if module == REGISTRY or module.startswith(REGISTRY + "."):  # the registry, what sits beside it, the settings
        return 2
    if top in HOST:
        return 3
    return None


def _package(module: str) -> str:
    """The unit whose circles count between packages: cdjax.<top>, or cdjax.agents.<setting>."""
    parts = module.split(".")
    if _setting_of(module) is not None:
        return ".".join(parts[:3])
    return ".".join(parts[:2])


def _known(imported: set[str]) -> set[str]:
    """The names of `imported` that are modules of cdjax (a name imported from outside it, misspelt, is not)."""
    return {name for name in imported if name in MODULES}


def _circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one node (Tarjan's algorithm), each sorted."""
    index, low, stack, on, found = {}, {}, [], set(), []

    def visit(node):
        index[node] = low[node] = len(index)
        stack.append(node)
        on.add(node)
        for nxt in sorted(graph.get(node, ())):
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = []
            while True:
                top = stack.pop()
                on.discard(top)
                component.append(top)
                if top == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def test_every_module_is_in_the_layer_table():
    unplaced = sorted(module for module in MODULES if _layer(module) is None)
    assert not unplaced, f"in no layer of the table (add their top-level names to SHARED or HOST): {unplaced}"


def test_no_import_runs_from_a_lower_layer_to_a_higher_one():
    upward = sorted(f"{module} (layer {_layer(module)}) imports {name} (layer {_layer(name)})"
                    for module, imported in MODULES.items() for name in _known(imported)
                    if None not in (_layer(name), _layer(module)) and _layer(name) > _layer(module))
    assert not upward, upward


def test_no_import_circle_between_modules_or_packages():
    modules = {module: {name for name in _known(imported) if name != module and not module.startswith(name + ".")}
               for module, imported in MODULES.items()}  # a submodule's import of its own package is no circle
    assert not _circles(modules), _circles(modules)
    packages: dict[str, set[str]] = {}
    for module, imported in modules.items():
        if module == FACE:
            continue
        packages.setdefault(_package(module), set()).update(
            _package(name) for name in imported if name != FACE and _package(name) != _package(module))
    assert not _circles(packages), _circles(packages)


def test_the_circle_finder_finds_circles():
    assert _circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _circles({"a": {"b"}, "b": set(), "c": {"c"}}) == []


def test_no_file_in_the_package_is_over_500_lines():
    long = sorted(f"{p.relative_to(ROOT.parent)}: {n}" for p in ROOT.rglob("*.py")
                  if (n := len(p.read_text().splitlines())) > MAX_LINES)
    assert not long, long
