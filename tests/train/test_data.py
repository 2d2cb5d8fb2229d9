"""Training data folders: one or several (a mix), visited in a seeded order."""

from __future__ import annotations

import pytest

from drivingscene.errors import InputError
from drivingscene.train.data import PairSequence, list_pairs


def _folder(root, name, seeds):
    folder = root / name
    folder.mkdir()
    for seed in seeds:
        (folder / f"pair_{seed:06d}.npz").write_bytes(b"")
    return folder


def test_several_folders_are_interleaved(tmp_path):
    a = _folder(tmp_path, "a", [0, 1, 2])
    b = _folder(tmp_path, "b", [5])
    files = list_pairs(f"{a},{b}")
    assert [f"{f.parent.name}/{f.stem}" for f in files] == ["a/pair_000000", "b/pair_000005", "a/pair_000001", "a/pair_000002"]
    assert list_pairs(a) == sorted(a.glob("pair_*.npz"))


def test_a_missing_or_empty_folder_is_named(tmp_path):
    a = _folder(tmp_path, "a", [0])
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="missing: expected a folder"):
        list_pairs(f"{a},{tmp_path / 'missing'}")
    with pytest.raises(InputError, match="empty: expected pair_"):
        list_pairs(f"{tmp_path / 'empty'}")


def test_sequence_visits_every_file_once_per_epoch(tmp_path):
    files = list_pairs(_folder(tmp_path, "a", range(7)))
    seq = PairSequence(files, seed=3)
    epoch = [seq.index(step) for step in range(7)]
    assert sorted(epoch) == list(range(7))
    assert [seq.index(step) for step in range(7, 14)] != epoch  # reshuffled each epoch
