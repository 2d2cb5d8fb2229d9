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


def module_name(path: Path, package: Path = PACKAGE) -> str:
    rel = path.relative_to(package.parent).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def import_circles(package: Path = PACKAGE) -> list[list[str]]:
    """Groups of modules that import each other, directly or around a loop (strongly connected
    components of the module graph, lazy imports inside functions included)."""
    modules = {module_name(p, package): p for p in sorted(package.rglob("*.py"))}
    edges: dict[str, set[str]] = {}
    for name, path in modules.items():
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            targets = []
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                targets = [f"{node.module}.{a.name}" if f"{node.module}.{a.name}" in modules else node.module for a in node.names]
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            edges.setdefault(name, set()).update(t for t in targets if t in modules and t != name)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    circles = []

    def visit(v: str) -> None:  # Tarjan's algorithm
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(edges.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                circles.append(sorted(group))

    for v in sorted(modules):
        if v not in index:
            visit(v)
    return circles


def test_no_module_imports_itself_around_a_circle():
    assert import_circles() == []


def test_the_circle_check_can_fail(tmp_path):
    package = tmp_path / "drivingscene"
    (package / "render").mkdir(parents=True)
    (package / "render" / "a.py").write_text("def f():\n    from drivingscene.render.b import g\n")
    (package / "render" / "b.py").write_text("from drivingscene.render import a\n")
    assert import_circles(package) == [["drivingscene.render.a", "drivingscene.render.b"]]


def test_a_reconstruction_imports_nothing_from_evaluation_benchmarks_or_training():
    """The inference path stays out of the evaluation room: reconstructing a pair loads no module
    of eval/, bench/ or train/ (checked in a fresh process: what it actually imports)."""
    import subprocess
    import sys

    code = (
        "import sys\n"
        "from drivingscene.methods.feedforward import load_model, reconstruct\n"
        "from tests.factories import make_pair\n"
        "reconstruct(load_model(), make_pair(2, 32, 48))\n"
        "print(sorted(m for m in sys.modules if m.split('.')[:2] in (['drivingscene', 'eval'], ['drivingscene', 'bench'], "
        "['drivingscene', 'train'])))\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip().splitlines()[-1] == "[]"


LONG_FILE_LINES = 500
REASON = "Why one file:"


def long_files_without_reason(roots: tuple[Path, ...] = (PACKAGE, VIEWER)) -> list[str]:
    """Modules longer than ``LONG_FILE_LINES`` whose docstring does not say why they stay one file."""
    bad = []
    for root in roots:
        for path in sorted(root.rglob("*.py")):
            text = path.read_text()
            if text.count("\n") <= LONG_FILE_LINES:
                continue
            doc = ast.get_docstring(ast.parse(text, str(path))) or ""
            if REASON not in doc:
                bad.append(f"{path.relative_to(root.parent)}: {text.count(chr(10))} lines")
    return bad


def test_a_long_module_says_why_it_is_one_file():
    assert long_files_without_reason() == []


def test_the_long_file_check_can_fail(tmp_path):
    body = "\n".join(f"x{i} = {i}" for i in range(LONG_FILE_LINES + 1)) + "\n"
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "long.py").write_text('"""A module."""\n' + body)
    (tmp_path / "pkg" / "reasoned.py").write_text(f'"""A module.\n\n{REASON} one table.\n"""\n' + body)
    (tmp_path / "pkg" / "short.py").write_text('"""A module."""\nx = 1\n')
    assert long_files_without_reason((tmp_path / "pkg",)) == [f"pkg/long.py: {LONG_FILE_LINES + 2} lines"]
