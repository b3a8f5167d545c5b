"""Every third-party module the package imports is provided by a distribution pyproject.toml declares.

A fresh machine installs exactly what pyproject.toml declares; a module that
only a developer's machine (or a warm cache) happens to have breaks both
README commands for a new user while CI stays green.
"""

import ast
import re
import sys
import tomllib
from importlib.metadata import packages_distributions
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _normalise(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def declared_distributions(pyproject: dict) -> set[str]:
    project = pyproject["project"]
    groups = [project.get("dependencies", [])] + list(project.get("optional-dependencies", {}).values())
    return {_normalise(re.split(r"[\s<>=!~\[;(]", req, maxsplit=1)[0]) for group in groups for req in group}


def imported_modules(source_dirs: list[Path], own: set[str]) -> dict[str, str]:
    """Top-level third-party module -> first 'file:line' importing it (imports inside functions included)."""
    found: dict[str, str] = {}
    for folder in source_dirs:
        for path in sorted(folder.rglob("*.py")):
            tree = ast.parse(path.read_text(), str(path))
            for node in ast.walk(tree):
                if isinstance(node, ast.Import):
                    names = [alias.name for alias in node.names]
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    names = [node.module]
                else:
                    continue
                for name in names:
                    top = name.split(".")[0]
                    if top not in sys.stdlib_module_names and top not in own:
                        found.setdefault(top, f"{path.relative_to(ROOT)}:{node.lineno}")
    return found


def undeclared_imports(pyproject: dict) -> dict[str, str]:
    package_dirs = pyproject["tool"]["setuptools"]["package-dir"]
    own = {"tacsplat"} | {Path(d).name for d in package_dirs.values()}
    declared = declared_distributions(pyproject)
    providers = packages_distributions()
    missing = {}
    for module, where in imported_modules([ROOT / d for d in sorted(set(package_dirs.values()))], own).items():
        # a module not installed here (an optional CUDA extra) counts as provided by the distribution of its name
        dists = {_normalise(d) for d in providers.get(module, [module])}
        if not dists & declared:
            missing[module] = f"{where} (installed by: {', '.join(sorted(dists))})"
    return missing


def test_every_imported_module_is_declared():
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    missing = undeclared_imports(pyproject)
    assert not missing, "imported but not declared in pyproject.toml: " + "; ".join(
        f"{m} at {w}" for m, w in missing.items()
    )


def test_the_check_catches_a_dependency_removed_from_pyproject():
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    sim = pyproject["project"]["optional-dependencies"]["sim"]
    pyproject["project"]["optional-dependencies"]["sim"] = [d for d in sim if not d.startswith("coacd")]
    assert "coacd" in undeclared_imports(pyproject)
