"""Where the perceptual-metric weights live, and how their keys map onto :class:`PerceptualMetric`.

Two sources, read as plain files (no third-party module is imported):

- ST-LPIPS: ``stlpips_pytorch/weights/vST0.0/{net}_shift_tolerant.pth`` from the
  ``stlpips-pytorch`` wheel (BSD-2), trunk + heads + scaling constants in one file. The package
  is located with ``importlib.util.find_spec`` (which does not execute it: its modules import
  torchvision and IPython).
- Original LPIPS v0.1: the torchvision ImageNet trunk (``alexnet-owt-7be5be79.pth`` /
  ``vgg16-397923af.pth``) and the LPIPS linear heads (``alex.pth`` / ``vgg.pth``). Searched, in
  order, in the folder given by the caller, in ``$DRIVINGSCENE_LPIPS_DIR``, then the trunk in the
  torch hub cache (``torch.hub.get_dir()/checkpoints``) and the heads in an installed ``lpips``
  package (``lpips/weights/v0.1``).
"""

from __future__ import annotations

import importlib.util
import os
import re
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from drivingscene.errors import DrivingSceneError

ENV_DIR = "DRIVINGSCENE_LPIPS_DIR"
TORCHVISION_FILES = {"alex": "alexnet-owt-7be5be79.pth", "vgg": "vgg16-397923af.pth"}
LPIPS_HEAD_FILES = {"alex": "alex.pth", "vgg": "vgg.pth"}

_ST_TRUNK_KEY = re.compile(r"net\.slice(\d)\.(\d+)\.(weight|bias|filt)")
_HEAD_KEY = re.compile(r"lin(\d)\.model\.1\.weight")
_TV_TRUNK_KEY = re.compile(r"features\.(\d+)\.(weight|bias)")


@dataclass(frozen=True)
class WeightFiles:
    """The files one metric is loaded from (``heads`` is None when ``trunk`` holds everything)."""

    kind: str  # "lpips" | "stlpips"
    net: str  # "alex" | "vgg"
    trunk: Path
    heads: Path | None


def _package_dir(name: str) -> Path | None:
    spec = importlib.util.find_spec(name)
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(next(iter(spec.submodule_search_locations)))


def stlpips_files(net: str) -> WeightFiles | None:
    """The ST-LPIPS weight file of ``net`` from the installed ``stlpips-pytorch`` wheel, if any."""
    root = _package_dir("stlpips_pytorch")
    if root is None:
        return None
    path = root / "weights" / "vST0.0" / f"{net}_shift_tolerant.pth"
    return WeightFiles("stlpips", net, path, None) if path.is_file() else None


def lpips_files(net: str, folder: str | os.PathLike | None = None) -> WeightFiles | None:
    """The original LPIPS trunk and head files of ``net``, if both are found (see module docstring)."""
    folders = [Path(f) for f in (folder, os.environ.get(ENV_DIR)) if f]
    trunk_dirs = folders + [Path(torch.hub.get_dir()) / "checkpoints"]
    head_dirs = list(folders)
    package = _package_dir("lpips")
    if package is not None:
        head_dirs.append(package / "weights" / "v0.1")
    trunk = next((d / TORCHVISION_FILES[net] for d in trunk_dirs if (d / TORCHVISION_FILES[net]).is_file()), None)
    heads = next((d / LPIPS_HEAD_FILES[net] for d in head_dirs if (d / LPIPS_HEAD_FILES[net]).is_file()), None)
    if trunk is None or heads is None:
        return None
    return WeightFiles("lpips", net, trunk, heads)


def _read(path: Path) -> dict[str, Tensor]:
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - any unreadable file is reported the same way
        raise DrivingSceneError(f"{path}: expected a torch state dict, could not read it: {type(e).__name__}") from None
    if not isinstance(state, dict):
        raise DrivingSceneError(f"{path}: expected a torch state dict, found {type(state).__name__}")
    return state


def _map_keys(
    path: Path, state: dict[str, Tensor], rules: list[tuple[re.Pattern, object]], ignore: re.Pattern | None = None
) -> dict[str, Tensor]:
    """Rename every key of ``state`` with the first rule whose pattern matches it fully.

    A rule is (pattern, function of the match returning our key, or None to reject the key).
    Keys that match no rule (and not ``ignore``) fail, so nothing is silently dropped.
    """
    mapped: dict[str, Tensor] = {}
    for key, value in state.items():
        if ignore is not None and ignore.fullmatch(key):
            continue
        ours = None
        for pattern, rename in rules:
            match = pattern.fullmatch(key)
            if match:
                ours = rename(match)
                break
        if ours is None:
            raise DrivingSceneError(f"{path}: unexpected weight key {key!r}")
        mapped[ours] = value
    return mapped


def _head_key(match: re.Match) -> str:
    return f"heads.{match.group(1)}.weight"


def stlpips_state(path: Path, taps: tuple[int, ...]) -> dict[str, Tensor]:
    """Our state dict from an ST-LPIPS file: ``net.sliceK.I.*`` -> ``features.I.*`` (I must lie in
    slice K of ``taps``), ``lin{k}.model.1.weight`` -> ``heads.{k}.weight``, ``scaling_layer.*``."""
    starts = (0,) + tuple(t + 1 for t in taps[:-1])

    def trunk_key(match: re.Match) -> str | None:
        k, index = int(match.group(1)) - 1, int(match.group(2))
        if not (0 <= k < len(taps) and starts[k] <= index <= taps[k]):
            return None
        return f"features.{index}.{match.group(3)}"

    scaling = re.compile(r"scaling_layer\.(shift|scale)")
    rules = [(_ST_TRUNK_KEY, trunk_key), (_HEAD_KEY, _head_key), (scaling, lambda m: m.group(1))]
    return _map_keys(path, _read(path), rules)


def lpips_state(trunk_path: Path, heads_path: Path) -> dict[str, Tensor]:
    """Our state dict from a torchvision trunk (``features.I.*``; the classifier is not used) and
    LPIPS v0.1 heads (``lin{k}.model.1.weight``). The scaling constants are not in these files."""
    trunk = _map_keys(
        trunk_path,
        _read(trunk_path),
        [(_TV_TRUNK_KEY, lambda m: m.group(0))],
        ignore=re.compile(r"classifier\..*"),
    )
    heads = _map_keys(heads_path, _read(heads_path), [(_HEAD_KEY, _head_key)])
    return trunk | heads


def check_state(described: str, expected: dict[str, Tensor], found: dict[str, Tensor]) -> None:
    """Fail with one line naming ``described`` unless ``found`` has exactly the keys and shapes of
    ``expected``."""
    missing = sorted(set(expected) - set(found))
    extra = sorted(set(found) - set(expected))
    if missing or extra:
        parts = []
        if missing:
            parts.append(f"missing {', '.join(missing[:4])}{' ...' if len(missing) > 4 else ''}")
        if extra:
            parts.append(f"unexpected {', '.join(extra[:4])}{' ...' if len(extra) > 4 else ''}")
        raise DrivingSceneError(f"{described}: weight keys do not match the network: {'; '.join(parts)}")
    for key, value in found.items():
        if tuple(value.shape) != tuple(expected[key].shape):
            raise DrivingSceneError(f"{described}: {key}: expected shape {list(expected[key].shape)}, found {list(value.shape)}")
