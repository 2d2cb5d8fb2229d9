"""Nothing is lost: every write is atomic (a temporary file beside the target, fsync, rename), a
process killed with SIGKILL at any moment leaves the old complete file or the new complete one,
nothing is overwritten without --force, and a folder that cannot be written is one clean line."""

from __future__ import annotations

import errno
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from drivingscene.data import atomic
from drivingscene.data.atomic import atomic_path, atomic_write, atomic_write_text
from drivingscene.errors import OutputError

ROOT = Path(__file__).resolve().parents[2]
OLD = b"old complete content\n"

# Calls that write a file under its final name; each must go through drivingscene.data.atomic.
WRITE_CALLS = re.compile(
    r"\.write_text\(|\.write_bytes\(|\bnp\.save(z|z_compressed)?\(|\bcv2\.imwrite\(|\.savefig\(|VideoWriter\(|"
    r"\btorch\.save\(|\.tofile\(|\bsave_file\(|\bopen\([^)]*[\"'][wax][bt+]*[\"']|os\.fdopen\([^)]*[\"'][wax]"
)
# A call whose target is the temporary path of `atomic_path` or an in-memory buffer is fine.
TO_TEMPORARY = re.compile(r"(imwrite|savefig|save|VideoWriter)\(\s*(str\()?(tmp|partial|buf)\b")
ALLOWED = {
    "drivingscene/data/atomic.py": "the helper itself: opens its own temporary file",
    "drivingscene/precision.py": "its cache is below data/ in the layers: the same temp + fsync + rename by hand, "
    "and a failure is only logged",
    "drivingscene/train/trainer.py": "append_jsonl: append-only logs; a torn last line is skipped on read "
    "(parse_jsonl_line) and the next append starts a new line (tests/reliability/test_atomic.py)",
}


def non_atomic_writes() -> list[str]:
    found = []
    for folder in ("drivingscene", "app"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            rel = path.relative_to(ROOT).as_posix()
            if rel in ALLOWED:
                continue
            for number, line in enumerate(path.read_text().splitlines(), 1):
                code = line.split("#", 1)[0]
                if WRITE_CALLS.search(code) and not TO_TEMPORARY.search(code):
                    found.append(f"{rel}:{number}: {line.strip()}")
    return found


def test_every_write_goes_through_the_atomic_helpers():
    assert non_atomic_writes() == [], "write through drivingscene.data.atomic (or add a reason to ALLOWED)"


def test_the_scan_finds_a_plain_write():
    assert WRITE_CALLS.search("out.write_text(report)") and WRITE_CALLS.search('with open(p, "w") as f:')
    assert not TO_TEMPORARY.search("cv2.imwrite(str(path), pixels)") and TO_TEMPORARY.search("cv2.imwrite(str(tmp), x)")


def test_failed_write_keeps_the_old_file_and_leaves_nothing(tmp_path):
    target = tmp_path / "out.bin"
    target.write_bytes(OLD)

    def half(f):
        f.write(b"new")
        raise RuntimeError("writer failed")

    with pytest.raises(RuntimeError):
        atomic_write(target, half)
    assert target.read_bytes() == OLD and os.listdir(tmp_path) == ["out.bin"]
    atomic_write_text(target, "new\n")
    assert target.read_text() == "new\n" and os.listdir(tmp_path) == ["out.bin"]


def test_path_writers_get_a_temporary_name_with_the_extension(tmp_path):
    with atomic_path(tmp_path / "a.png") as tmp:
        assert tmp.parent == tmp_path and tmp.name.startswith(".a.png.") and tmp.suffix == ".png"
        tmp.write_bytes(b"png")
    assert (tmp_path / "a.png").read_bytes() == b"png" and os.listdir(tmp_path) == ["a.png"]


def test_stale_temporary_files_of_a_dead_process_are_removed(tmp_path):
    target = tmp_path / "r.npz"
    stale = tmp_path / ".r.npz.999999999.abcd.tmp"  # no such pid
    live = tmp_path / f".r.npz.{os.getpid()}.efgh.tmp"  # a writer still running
    young = tmp_path / ".r.npz.999999998.ijkl.tmp"
    for p in (stale, live, young):
        p.write_bytes(b"x")
    old = time.time() - 2 * atomic.STALE_SECONDS
    os.utime(stale, (old, old))
    os.utime(live, (old, old))
    atomic_write_text(target, "new")
    assert not stale.exists() and live.exists() and young.exists()


def test_full_disk_is_a_clean_error_without_a_partial_file(tmp_path, monkeypatch):
    target = tmp_path / "out.bin"
    target.write_bytes(OLD)

    def no_space(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(atomic.os, "fsync", no_space)
    with pytest.raises(OutputError, match=r"out\.bin: could not write it: No space left on device"):
        atomic_write_text(target, "new")
    assert target.read_bytes() == OLD and os.listdir(tmp_path) == ["out.bin"]


def test_unwritable_places_are_clean_errors(tmp_path):
    (tmp_path / "file").write_bytes(OLD)
    with pytest.raises(OutputError, match="could not write it"):
        atomic_write_text(tmp_path / "file" / "out.txt", "x")  # a file where the folder should be
    with pytest.raises(OutputError, match="could not write it"):
        atomic_write_text("/proc/self/drivingscene_out.txt", "x")  # /proc refuses new files, even to root
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    with pytest.raises(OutputError, match="not a regular file"):
        atomic_write_text(fifo, "x")  # like /dev/full: never renamed over
    assert fifo.is_fifo()
    if Path("/dev/full").is_char_device():  # the device itself, where there is one
        with pytest.raises(OutputError, match="/dev/full: could not write it: not a regular file"):
            atomic_write_text("/dev/full", "x")
        assert Path("/dev/full").is_char_device()


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into a chmod 0o555 folder: the test below drops its override")
def test_read_only_folder_is_a_clean_error(tmp_path):
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        with pytest.raises(OutputError, match="Permission denied"):
            atomic_write_text(folder / "out.txt", "x")
        assert os.listdir(folder) == []
    finally:
        folder.chmod(0o755)


@pytest.mark.skipif(
    os.geteuid() != 0 or shutil.which("setpriv") is None, reason="root with setpriv only (others: the test above)"
)
def test_read_only_folder_stops_root_without_its_override(tmp_path):
    """As root (CI's and these machines' user) a 0o555 folder is writable, so the command runs without
    the capabilities that let root ignore permissions (setpriv drops them from its bounding set), as
    any other user would: one line naming the target, exit code 2, nothing left in the folder."""
    from drivingscene.data import save_frame_pair
    from tests.factories import make_pair

    scene = tmp_path / "pair.npz"
    save_frame_pair(make_pair(num_views=2, height=12, width=16), scene)
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o555)
    target = folder / "out.npz"
    drop = "--bounding-set=-dac_override,-dac_read_search"
    try:
        run = subprocess.run(
            ["setpriv", drop, sys.executable, "-m", "drivingscene", "oracle", str(scene), "-o", str(target)],
            capture_output=True, text=True, timeout=300,
        )  # fmt: skip
        assert run.returncode == 2, run.stderr
        lines = run.stderr.strip().splitlines()
        assert len(lines) == 1 and str(target) in lines[0] and "Permission denied" in lines[0], run.stderr
        assert os.listdir(folder) == []
    finally:
        folder.chmod(0o755)


def test_append_only_log_tolerates_a_torn_last_line(tmp_path):
    from drivingscene.bench.training_report import _read_jsonl
    from drivingscene.train.trainer import _truncate_log, append_jsonl

    log = tmp_path / "log.jsonl"
    append_jsonl(log, {"step": 1})
    with open(log, "ab") as f:  # a run killed mid-append
        f.write(b'{"step": 2, "lo')
    append_jsonl(log, {"step": 2})
    assert [r["step"] for r in _read_jsonl(log)] == [1, 2]
    _truncate_log(log, 1)
    assert log.read_text() == '{"step": 1}\n'


def test_rig_export_is_renamed_into_place_whole(tmp_path, monkeypatch):
    """An exported rig folder appears complete or not at all; it never lands on a folder with files."""
    import drivingscene.data.importers.rig_export as rig_export
    from drivingscene.data.importers.rig import import_rig
    from tests.factories import make_pair

    pair = make_pair(num_views=2, height=12, width=16)
    calls = {"n": 0}
    write_png = rig_export._write_png

    def failing(path, image):  # the third image fails, as a full disk or a kill would stop the export
        calls["n"] += 1
        if calls["n"] == 3:
            raise OutputError(f"{path}: could not write the PNG")
        return write_png(path, image)

    monkeypatch.setattr(rig_export, "_write_png", failing)
    with pytest.raises(OutputError):
        rig_export.export_rig(pair, tmp_path / "rig")
    assert list(tmp_path.iterdir()) == []  # no rig, no half-written folder, no staging left
    monkeypatch.setattr(rig_export, "_write_png", write_png)
    path = rig_export.export_rig(pair, tmp_path / "rig")
    assert path == tmp_path / "rig" / "rig.json" and [p.name for p in tmp_path.iterdir()] == ["rig"]
    assert import_rig(tmp_path / "rig", (0, 1), (), None, "crop").num_views == 2
    with pytest.raises(OutputError, match="expected a new or empty folder"):
        rig_export.export_rig(pair, tmp_path / "rig")  # files in it: refused, left as it was
    assert path.is_file() and [p.name for p in tmp_path.iterdir()] == ["rig"]
