"""The hand-off of a GPU reconstruction to the CPU before the assembly (`feedforward._on_cpu`), and
the one-line errors of the benchmarks' ``--device``."""

from __future__ import annotations

from dataclasses import dataclass

import pytest
import torch

from drivingscene.cli import main
from drivingscene.data.tensors import pair_to_tensors
from drivingscene.methods.feedforward import _on_cpu
from tests.factories import make_pair


@dataclass
class _Inner:
    a: torch.Tensor
    items: list


@dataclass
class _Outer:
    inner: _Inner
    maybe: torch.Tensor | None
    table: dict


def test_every_tensor_of_a_nested_structure_lands_on_the_cpu_and_the_structure_stays():
    device = "cuda" if torch.cuda.is_available() else "cpu"
    x = torch.arange(6.0, device=device)
    batch = pair_to_tensors(make_pair(num_views=2, height=8, width=12), with_gt=False, with_eval=False).to(device)
    value = _Outer(_Inner(x, [x, (x, 3)]), None, {"k": x, "s": "text"})
    moved, moved_batch, nothing = _on_cpu((value, batch, None))
    assert type(moved) is _Outer and type(moved.inner) is _Inner and type(moved_batch) is type(batch)
    tensors = [moved.inner.a, moved.inner.items[0], moved.inner.items[1][0], moved.table["k"], moved_batch.images]
    assert all(t.device.type == "cpu" for t in tensors)
    assert torch.equal(moved.inner.a, x.cpu()) and moved.inner.items[1][1] == 3 and moved.table["s"] == "text"
    assert isinstance(moved.inner.items[1], tuple) and moved.maybe is None and nothing is None
    assert torch.equal(moved_batch.images, batch.images.cpu())


@pytest.mark.parametrize("command", [["bench", "choices", "--data", "d"], ["bench", "inference", "--sizes", "24x40"]])
def test_benchmark_device_errors_are_one_line(capsys, command):
    assert main(command + ["--device", "tpu"]) == 2
    err = capsys.readouterr().err
    assert "--device: expected cpu, cuda or cuda:N, found 'tpu'" in err and err.count("\n") == 1
