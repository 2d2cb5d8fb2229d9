"""Training data: a folder of frame-pair files, visited in a seeded order that depends only on
(seed, epoch), so a resumed run sees the same sequence without saved iterator state."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from drivingscene.data.frame_pair import load_frame_pair
from drivingscene.data.tensors import PairTensors, pair_to_tensors
from drivingscene.errors import InputError
from drivingscene.train.config import TrainConfig


def list_pairs(folders: str | Path) -> list[Path]:
    """The pair files of a folder, or of several folders given as one string separated by commas
    (training on a mix of datasets: ``data/train96,data/train96r``), interleaved folder by folder
    (so that the first N files, e.g. validation pairs, come from every folder)."""
    per_folder = [_folder_pairs(Path(f)) for f in str(folders).split(",") if f]
    if not per_folder:
        raise InputError(f"{folders!r}: expected a folder of pair_*.npz files (drivingscene synth --split train --out DIR)")
    longest = max(len(files) for files in per_folder)
    return [files[i] for i in range(longest) for files in per_folder if i < len(files)]


def pair_files(path: Path, count: int | None = None) -> list[Path]:
    """``[path]`` for a pair file, else the pairs of the folder ``path`` (`list_pairs`), the first
    ``count`` of them (None: all); a path that is neither is an `InputError` naming it."""
    return [path] if path.is_file() else list_pairs(path)[:count]


def _folder_pairs(folder: Path) -> list[Path]:
    if not folder.is_dir():
        raise InputError(f"{folder}: expected a folder of pair_*.npz files (drivingscene synth --split train --out DIR)")
    files = sorted(folder.glob("pair_*.npz"))
    if not files:
        raise InputError(f"{folder}: expected pair_*.npz files, found none")
    return files


class PairSequence:
    """Infinite, deterministic sequence of pairs for one process of a (possibly distributed) run."""

    def __init__(self, files: list[Path], seed: int, rank: int = 0, world: int = 1):
        self.files = files
        self.seed = seed
        self.rank = rank
        self.world = world

    def index(self, step: int, slot: int = 0, per_step: int = 1) -> int:
        """File index for a global step (each step consumes world * per_step files)."""
        n = len(self.files)
        position = (step * self.world + self.rank) * per_step + slot
        epoch, offset = divmod(position, n)
        order = np.random.default_rng([self.seed, epoch]).permutation(n)
        return int(order[offset])

    def get(self, step: int, slot: int = 0, per_step: int = 1) -> PairTensors:
        return pair_to_tensors(load_frame_pair(self.files[self.index(step, slot, per_step)]))


def with_data_size(config: TrainConfig, files: list[Path]) -> TrainConfig:
    """The config with the model's ``input_size`` set to the training images' size."""
    if config.model.input_size is not None:
        return config
    size = load_frame_pair(files[0]).image_size
    return replace(config, model=replace(config.model, input_size=size))
