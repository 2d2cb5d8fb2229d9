"""The packages of drivingscene run downward: each imports only packages below it in LAYERS (read
from the source with ast, so lazy imports inside functions count too), and the library never
imports the viewer. docs/architecture.md describes the same order."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "drivingscene"
VIEWER = ROOT / "app"

# Bottom first. A package may import the packages before it, never one after it.
LAYERS = (
    "errors",
    "resources",
    "precision",
    "machine",
    "arguments",
    "kernels",
    "geometry",
    "data",
    "gaussians",
    "render",
    "export",
    "gl",
    "viz",
    "synth",
    "eval",
    "sources",
    "models",
    "methods",
    "train",
    "bench",
    "cli",
    "__main__",
)


def unit_of(path: Path, package: Path = PACKAGE) -> str:
    """The top-level unit of drivingscene a file belongs to (a subpackage or a module)."""
    rel = path.relative_to(package).with_suffix("")
    return rel.parts[0]


def imported_modules(path: Path) -> list[tuple[int, str]]:
    """``(line, module)`` of every absolute import in ``path``."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.append((node.lineno, node.module))
        elif isinstance(node, ast.Import):
            out.extend((node.lineno, alias.name) for alias in node.names)
    return out


def upward_imports(package: Path = PACKAGE) -> list[str]:
    rank = {name: i for i, name in enumerate(LAYERS)}
    bad = []
    for path in sorted(package.rglob("*.py")):
        unit = unit_of(path, package)
        if unit == "__init__":
            continue  # the package's own __init__ (checked below)
        for line, module in imported_modules(path):
            parts = module.split(".")
            if parts[0] == "drivingscene_view":
                bad.append(f"{path.relative_to(package.parent)}:{line} imports the viewer ({module})")
            if parts[0] != "drivingscene" or len(parts) < 2 or parts[1] == unit:
                continue
            if rank[parts[1]] > rank[unit]:
                bad.append(f"{path.relative_to(package.parent)}:{line}: {unit} imports {module}, which sits above it")
    return bad


def test_every_unit_has_a_layer():
    units = {unit_of(p) for p in PACKAGE.rglob("*.py")} - {"__init__"}
    assert units <= set(LAYERS), f"add to LAYERS (and docs/architecture.md): {sorted(units - set(LAYERS))}"


def test_packages_import_only_downward():
    assert upward_imports() == []


def test_package_init_imports_nothing_heavy():
    """``import drivingscene`` stays cheap: its __init__ imports at most the error types."""
    modules = {m for _, m in imported_modules(PACKAGE / "__init__.py") if m.startswith("drivingscene")}
    assert modules <= {"drivingscene.errors"}


@pytest.mark.parametrize("package", ["cli", "train"])
def test_viewer_imports_neither_the_command_line_nor_training(package):
    """The viewer takes its argument grammar from drivingscene.arguments, not from cli/, and runs
    inference, never training code."""
    bad = [
        f"{p.relative_to(ROOT)}:{line} {m}"
        for p in sorted(VIEWER.rglob("*.py"))
        for line, m in imported_modules(p)
        if m == f"drivingscene.{package}" or m.startswith(f"drivingscene.{package}.")
    ]
    assert bad == []


@pytest.mark.parametrize("unit", ["bench", "cli"])
def test_layer_check_can_fail(tmp_path, unit):
    """A planted upward import is found (the check is not vacuous)."""
    package = tmp_path / "drivingscene"
    (package / "geometry").mkdir(parents=True)
    (package / "geometry" / "bad.py").write_text(f"from drivingscene.{unit}.x import y\n")
    found = upward_imports(package)
    assert len(found) == 1 and f"imports drivingscene.{unit}.x" in found[0]
