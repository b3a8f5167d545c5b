"""The layers read bottom to top (DESIGN.md): an import graph over every module, imports inside functions included.

core (tacsplat/errors, geometry, types) -> datasets -> drivers, reconstruction -> sim -> acquisition
-> applications (tacsplat/apps) -> the CLI (tacsplat/cli.py, tacsplat/__main__.py).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGE_DIRS = {  # import prefix -> folder (pyproject's package-dir)
    "tacsplat.drivers": "drivers",
    "tacsplat.sim": "sim",
    "tacsplat.acquisition": "acquisition",
    "tacsplat.reconstruction": "reconstruction",
    "tacsplat.datasets": "datasets",
    "tacsplat": "tacsplat",
}
CORE = {
    "tacsplat",
    "tacsplat.config_files",
    "tacsplat.errors",
    "tacsplat.files",
    "tacsplat.geometry",
    "tacsplat.types",
    "tacsplat.progress",
    "tacsplat.interrupts",
    "tacsplat.options",
}
# the layer of each subpackage; a module may import only its own layer or lower ones
LAYERS = {
    "core": 0,
    "tacsplat.datasets": 1,
    "tacsplat.drivers": 2,
    "tacsplat.reconstruction": 2,
    "tacsplat.sim": 3,
    "tacsplat.acquisition": 4,
    "tacsplat.apps": 5,
    "cli": 6,
}
# same-layer neighbours that must not know each other
FORBIDDEN_PAIRS = {("tacsplat.drivers", "tacsplat.reconstruction"), ("tacsplat.reconstruction", "tacsplat.drivers")}
ONLY_UNDER = {"mujoco": "tacsplat.sim", "dynamixel_sdk": "tacsplat.drivers", "serial": "tacsplat.drivers"}
CLI_MODULES = {"tacsplat.cli", "tacsplat.__main__"}


def module_files() -> dict[str, Path]:
    modules = {}
    for prefix, folder in PACKAGE_DIRS.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            rel = path.relative_to(ROOT / folder).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            modules[".".join([prefix, *parts])] = path
    return modules


def imports_of(name: str, path: Path, modules: dict[str, Path]) -> list[tuple[str, int, str]]:
    """(imported module or 'importlib', line, kind) for every import in the file; relative imports resolved."""
    tree = ast.parse(path.read_text(), str(path))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(alias.name, node.lineno, "import") for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")
                anchor = anchor[: len(anchor) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            for alias in node.names:  # `from pkg import module` imports the module
                full = f"{base}.{alias.name}"
                found.append((full if full in modules else base, node.lineno, "import"))
        elif isinstance(node, ast.Call):
            func = node.func
            if (isinstance(func, ast.Attribute) and func.attr == "import_module") or (
                isinstance(func, ast.Name) and func.id in ("import_module", "__import__")
            ):
                found.append(("importlib", node.lineno, "dynamic"))
    return found


def layer_of(module: str) -> str:
    if module in CLI_MODULES:
        return "cli"
    if module in CORE:
        return "core"
    for prefix in ("tacsplat.apps", *PACKAGE_DIRS):
        if prefix != "tacsplat" and (module == prefix or module.startswith(prefix + ".")):
            return prefix
    return "tacsplat.apps"  # any other module of tacsplat/ is an application


@pytest.fixture(scope="module")
def graph():
    modules = module_files()
    edges = {}
    for name, path in modules.items():
        edges[name] = imports_of(name, path, modules)
    return modules, edges


def test_no_import_cycles_between_modules(graph):
    modules, edges = graph
    internal = {m: sorted({t for t, _, k in e if t in modules and t != m}) for m, e in edges.items()}
    cycles, state, stack = [], {}, []

    def visit(node):
        state[node] = "open"
        stack.append(node)
        for nxt in internal[node]:
            if state.get(nxt) == "open":
                cycles.append(stack[stack.index(nxt) :] + [nxt])
            elif nxt not in state:
                visit(nxt)
        stack.pop()
        state[node] = "done"

    for node in internal:
        if node not in state:
            visit(node)
    assert not cycles, "import cycles: " + "; ".join(" -> ".join(c) for c in cycles)


def test_every_module_imports_only_its_own_layer_or_lower(graph):
    modules, edges = graph
    bad = []
    for name, imported in edges.items():
        mine = layer_of(name)
        for target, line, kind in imported:
            if kind != "import" or not target.startswith("tacsplat"):
                continue
            theirs = layer_of(target)
            if LAYERS[theirs] > LAYERS[mine] or (mine, theirs) in FORBIDDEN_PAIRS:
                bad.append(f"{modules[name].relative_to(ROOT)}:{line} ({mine}) imports {target} ({theirs})")
            elif mine == "core" and target not in CORE:
                bad.append(f"{modules[name].relative_to(ROOT)}:{line}: a core file imports {target}")
    assert not bad, "imports against the layers:\n" + "\n".join(bad)


def test_simulator_and_hardware_packages_stay_in_their_layer(graph):
    modules, edges = graph
    bad = []
    for name, imported in edges.items():
        for target, line, _ in imported:
            home = ONLY_UNDER.get(target.split(".")[0])
            if home and not name.startswith(home):
                bad.append(f"{modules[name].relative_to(ROOT)}:{line} imports {target} (only {home} may)")
    assert not bad, "\n".join(bad)


def test_importlib_loads_only_in_the_cli_dispatcher(graph):
    modules, edges = graph
    bad = [
        f"{modules[name].relative_to(ROOT)}:{line}"
        for name, imported in edges.items()
        for target, line, kind in imported
        if kind == "dynamic" and name not in CLI_MODULES
    ]
    assert not bad, "importlib loads outside tacsplat/cli.py: " + ", ".join(bad)
