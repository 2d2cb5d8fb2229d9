"""Writing datasets of generated pairs: ``DIR/pair_<seed>.npz`` plus ``DIR/manifest.json``.

Every file is written atomically, so a file that exists is complete; resuming an interrupted run
skips them. A folder whose manifest has a different split or config is refused, unless ``force``
regenerates every pair it records.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Callable, Iterable
from pathlib import Path

from drivingscene import __version__
from drivingscene.data import FORMAT_VERSION, save_frame_pair
from drivingscene.data.npz import atomic_write
from drivingscene.errors import InputError
from drivingscene.synth.config import SynthConfig

log = logging.getLogger(__name__)

MANIFEST = "manifest.json"
DATASET_FORMAT = "drivingscene/synth-dataset"
DATASET_VERSION = 1


def pair_path(folder: str | os.PathLike, seed: int) -> Path:
    return Path(folder) / f"pair_{seed:06d}.npz"


def _manifest(split: str, seeds: list[int], config: SynthConfig) -> dict:
    return {
        "format": DATASET_FORMAT,
        "version": DATASET_VERSION,
        "scene_format_version": FORMAT_VERSION,
        "generator": f"drivingscene {__version__}",
        "split": split,
        "config": config.to_dict(),
        "seeds": seeds,
    }


def _check_existing(folder: Path, split: str, config: SynthConfig) -> tuple[list[int], str | None]:
    """Seeds already recorded in ``folder``'s manifest, and how the folder was made differently
    (a one-line reason) or None."""
    path = folder / MANIFEST
    if not path.exists():
        return [], None
    try:
        old = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise InputError(f"{path}: expected a dataset manifest (JSON), could not read it: {e}") from None
    if old.get("format") != DATASET_FORMAT:
        raise InputError(f"{path}: expected a {DATASET_FORMAT} manifest, found format {old.get('format')!r}")
    seeds = [int(s) for s in old.get("seeds", [])]
    if old.get("split") != split:
        return seeds, f"holds split {old.get('split')!r}, not {split!r}"
    new = config.to_dict()
    # knobs added since the folder was written had their default value then
    recorded = {**SynthConfig().to_dict(), **old.get("config", {})}
    diff = [k for k in sorted(set(new) | set(recorded)) if recorded.get(k) != new.get(k)]
    if diff:
        k = diff[0]
        return seeds, f"was generated with a different config ({k}={recorded.get(k)!r} there, {new.get(k)!r} now)"
    return seeds, None


def _remove_stale_temporaries(folder: Path) -> None:
    """Temporary files left by a killed run (atomic_write names them ``.<name>.<random>.tmp``)."""
    for tmp in folder.glob(".pair_*.npz.*.tmp"):
        tmp.unlink(missing_ok=True)


def write_dataset(
    folder: str | os.PathLike,
    split: str,
    seeds: Iterable[int],
    config: SynthConfig,
    generate: Callable[[int], object],
    progress: bool = True,
    force: bool = False,
) -> tuple[int, int]:
    """Generate every seed of ``seeds`` into ``folder`` (skipping files that exist).

    ``generate(seed)`` returns a ``FramePair``. ``force``: regenerate the pairs that exist too, and
    accept a folder made with another split or config when every pair it records is among
    ``seeds`` (all of them are then made anew; otherwise the folder is refused, as without it).
    Returns (pairs written, pairs skipped).
    """
    from tqdm import tqdm

    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise InputError(f"--out: expected a folder for a dataset, found a file {folder}")
    seeds = list(seeds)
    recorded, different = _check_existing(folder, split, config)
    if different is not None:
        kept = sorted(set(recorded) - set(seeds))
        if not force:
            raise InputError(f"--out: {folder} {different}; use another folder, the same flags or --force")
        if kept:
            raise InputError(
                f"--out: {folder} {different}, and --force would leave {len(kept)} of its pairs (seed {kept[0]}"
                f"{', ...' if len(kept) > 1 else ''}) made the old way; use another folder or --count/--start covering them"
            )
        recorded = []
    folder.mkdir(parents=True, exist_ok=True)
    _remove_stale_temporaries(folder)
    manifest = _manifest(split, sorted(set(recorded) | set(seeds)), config)
    atomic_write(folder / MANIFEST, lambda f: f.write((json.dumps(manifest, indent=1) + "\n").encode()), suffix=".tmp")
    written = skipped = 0
    bar = tqdm(seeds, desc=f"synth {split}", unit="pair", disable=not progress)
    for seed in bar:
        path = pair_path(folder, seed)
        if path.exists() and not force:
            skipped += 1
            continue
        save_frame_pair(generate(seed), path)
        written += 1
    log.info("%s: %d pairs written, %d already there", folder, written, skipped)
    return written, skipped
