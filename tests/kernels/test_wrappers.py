"""Every op the C++ sources register has a typed wrapper in drivingscene.kernels; only
drivingscene/kernels reaches the ops by name; `available` keeps the backend semantics."""

from __future__ import annotations

import inspect
import re
from pathlib import Path

import pytest
import torch

from drivingscene import kernels
from drivingscene.kernels import build

ROOT = Path(__file__).resolve().parents[2]
CSRC = ROOT / "drivingscene" / "kernels" / "csrc"
SCHEMA_TYPES = {"Tensor": "Tensor", "int": "int", "float": "float", "bool": "bool"}


def registered_schemas() -> dict[str, list[tuple[str, str]]]:
    """``m.def("name(Type arg, ...) -> ...")`` of every csrc/*.cpp: op name -> [(type, argument)]."""
    schemas = {}
    for source in sorted(CSRC.glob("*.cpp")):
        for literals in re.findall(r'm\.def\(\s*((?:"[^"]*"\s*)+)', source.read_text()):
            schema = "".join(re.findall(r'"([^"]*)"', literals))
            name, args = re.match(r"(\w+)\((.*?)\)\s*->", schema).groups()
            schemas[name] = [tuple(arg.split()) for arg in args.split(",")]
    return schemas


def test_the_sources_register_the_ops_we_know():
    schemas = registered_schemas()
    assert (
        len(schemas) == 20
        and "composite_backward" in schemas
        and "own_layer_solve" in schemas
        and "find_pairs" in schemas
        and "pixel_footprints" in schemas
        and "plane_sweep_correlate_backward" in schemas
    )


@pytest.mark.parametrize("name", sorted(registered_schemas()))
def test_every_registered_op_has_a_documented_wrapper_with_its_signature(name):
    wrapper = kernels.OPS.get(name)
    assert wrapper is not None, f"{name}: no wrapper in drivingscene.kernels"
    assert getattr(kernels, name) is wrapper and name in kernels.__all__
    assert "Reference path" in (wrapper.__doc__ or ""), f"{name}: the docstring names no torch reference path"
    params = inspect.signature(wrapper).parameters
    expected = [(arg, SCHEMA_TYPES[kind]) for kind, arg in registered_schemas()[name]]
    assert [(p.name, p.annotation) for p in params.values()] == expected
    assert all(p.kind is inspect.Parameter.POSITIONAL_OR_KEYWORD for p in params.values())


def test_no_wrapper_without_a_registered_op():
    assert set(kernels.OPS) == set(registered_schemas())


# Reaching the ops by name (or through the removed loader module) is kept to drivingscene/kernels.
FORBIDDEN = ("drivingscene_render", "select_op(", "load_op(", "render.cpp", "render import cpp", "kernels.build")


def test_only_the_kernels_package_reaches_the_ops_by_name():
    offenders = []
    for folder in ("drivingscene", "app"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            if (ROOT / "drivingscene" / "kernels") in path.parents:
                continue
            text = path.read_text()
            offenders += [f"{path.relative_to(ROOT)}: {word}" for word in FORBIDDEN if word in text]
    assert not offenders


def test_available_follows_the_backend_choice(monkeypatch):
    cpu = torch.zeros(2, 3)
    assert not kernels.available(kernels.fb_consistent, "torch", cpu)
    assert not kernels.available(kernels.fb_consistent, "auto", cpu.double())  # float32 only
    assert not kernels.available(kernels.fb_consistent, "auto", cpu.requires_grad_())  # no backward
    with pytest.raises(ValueError, match="backend"):
        kernels.available(kernels.fb_consistent, "fast", cpu)
    with pytest.raises(ValueError, match="not a compiled-kernel wrapper"):
        kernels.available(torch.add, "auto", cpu)
    monkeypatch.setattr(build, "load_extension", lambda: False)
    assert not kernels.available(kernels.fb_consistent, "auto", torch.zeros(2, 3))
    with pytest.raises(RuntimeError, match="fb_consistent: the compiled kernel is unavailable"):
        kernels.available(kernels.fb_consistent, "cpp", torch.zeros(2, 3))
    with pytest.raises(RuntimeError, match="fb_consistent: the compiled kernel is unavailable"):
        kernels.fb_consistent(torch.zeros(1, 2, 2, 2), torch.zeros(1, 2, 2, 2), 0.01, 0.5)


def test_available_chooses_the_compiled_op_where_it_builds(compiled_kernels):
    assert compiled_kernels.available(compiled_kernels.fb_consistent, "auto", torch.zeros(2, 3))
    assert compiled_kernels.available(compiled_kernels.fb_consistent, "cpp", torch.zeros(2, 3, dtype=torch.float64))


def test_the_kernels_package_stands_on_the_ground_floor():
    for path in sorted((ROOT / "drivingscene" / "kernels").glob("*.py")):
        imports = re.findall(r"^\s*(?:from|import) (drivingscene[\w.]*)", path.read_text(), re.MULTILINE)
        assert all(m == "drivingscene.errors" or m.startswith("drivingscene.kernels") for m in imports), (path.name, imports)
