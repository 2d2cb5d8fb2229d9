"""The hand-off of a GPU reconstruction to the CPU before the assembly (`methods.devices.on_cpu`), and
the one-line errors of the benchmarks' ``--device``."""

from __future__ import annotations

from dataclasses import dataclass

import pytest
import torch

from drivingscene.cli import main
from drivingscene.data.tensors import pair_to_tensors
from drivingscene.methods.devices import on_cpu
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
    moved, moved_batch, nothing = on_cpu((value, batch, None))
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


def test_load_model_built_on_the_meta_device_holds_what_the_usual_build_holds(tmp_path):
    """`load_model` builds the networks on the meta device and assigns the file's tensors; the model
    is the one the usual build and `load_state_dict` make, and a file without a tensor is still an error."""
    import json

    from safetensors.torch import load_file, save_file

    from drivingscene.errors import InputError
    from drivingscene.methods.feedforward import DEFAULT_WEIGHTS, load_model
    from drivingscene.models.model import DrivingSceneModel, ModelConfig
    from drivingscene.resources import asset_path

    path = asset_path(DEFAULT_WEIGHTS)
    model = load_model(path)
    usual = DrivingSceneModel(ModelConfig.from_dict(json.loads(path.with_suffix(".json").read_text())["model"]))
    usual.load_state_dict(load_file(str(path)))
    ours, theirs = dict(model.named_buffers()), dict(usual.named_buffers())
    assert ours.keys() == theirs.keys() and all(torch.equal(ours[k], theirs[k]) for k in ours)  # non-persistent too
    params, reference = dict(model.named_parameters()), dict(usual.named_parameters())
    assert params.keys() == reference.keys()
    assert all(p.dtype == torch.float32 and p.requires_grad and torch.equal(p, reference[k]) for k, p in params.items())
    assert not model.training
    state = load_file(str(path))
    state.pop(next(k for k in state if k.endswith(".weight")))  # BatchNorm fills a missing step count in itself
    save_file(state, str(tmp_path / "w.safetensors"))
    (tmp_path / "w.json").write_text(path.with_suffix(".json").read_text())
    with pytest.raises(InputError, match="missing 1"):
        load_model(tmp_path / "w.safetensors")
