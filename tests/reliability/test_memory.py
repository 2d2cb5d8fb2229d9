"""Inputs that would not fit in memory are refused (or downscaled on request) before any large
allocation, with one line that says how to proceed (issue 20)."""

from __future__ import annotations

import io
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import numpy as np
import pytest

from drivingscene.data import FramePair
from drivingscene.data.frame_pair import load_frame_pair, save_frame_pair
from drivingscene.errors import InputError
from drivingscene.machine import MEMORY_LIMIT_ENV, available_memory_bytes
from drivingscene.methods.memory import check_reconstruct_memory, fitting_scale, reconstruct_bytes
from tests.factories import make_pair


def _forged_scene(path: Path, shape: tuple[int, ...], small: FramePair) -> Path:
    """``small``'s arrays, except that images.npy declares ``shape`` and holds 64 bytes."""
    with zipfile.ZipFile(path, "w") as zf:
        for key, value in small.to_arrays().items():
            buf = io.BytesIO()
            if key == "images":
                np.lib.format.write_array_header_1_0(buf, {"descr": "|u1", "fortran_order": False, "shape": shape})
                buf.write(b"\0" * 64)
            else:
                np.lib.format.write_array(buf, np.asarray(value), allow_pickle=False)
            zf.writestr(f"{key}.npy", buf.getvalue())
    return path


def test_limit_override(monkeypatch):
    monkeypatch.setenv(MEMORY_LIMIT_ENV, "8G")
    assert available_memory_bytes() == 8 * 2**30
    monkeypatch.setenv(MEMORY_LIMIT_ENV, "12345")
    assert available_memory_bytes() == 12345
    monkeypatch.setenv(MEMORY_LIMIT_ENV, "lots")
    with pytest.raises(InputError, match=MEMORY_LIMIT_ENV):
        available_memory_bytes()
    monkeypatch.delenv(MEMORY_LIMIT_ENV)
    assert available_memory_bytes() > 0


def test_estimate_is_linear_in_pixels_and_covers_the_measurements():
    measured_mib = {(96, 176): 253, (176, 320): 279, (352, 640): 803, (528, 960): 1716, (704, 1280): 2870}
    for (h, w), mib in measured_mib.items():
        estimate = reconstruct_bytes(6, h, w) / 2**20
        assert mib <= estimate <= 1.5 * mib + 100
    assert reconstruct_bytes(12, 1080, 1920) > 13 * 2**30
    assert reconstruct_bytes(6, 100, 100, refine=True) > reconstruct_bytes(6, 100, 100)


def test_twelve_cameras_full_hd_refused_with_message(monkeypatch):
    monkeypatch.setenv(MEMORY_LIMIT_ENV, "8G")
    with pytest.raises(InputError) as e:
        check_reconstruct_memory(12, 1080, 1920, "big.npz", flag="--scale")
    message = str(e.value)
    assert "\n" not in message
    assert message.startswith("big.npz: images: 12 cameras at 1080x1920 need about 14.")
    assert "8.0 GiB available" in message and "--scale 0.7" in message and "--scale auto" in message
    scale = fitting_scale(12, 1080, 1920, 8 * 2**30)
    assert reconstruct_bytes(12, round(1080 * scale), round(1920 * scale)) <= 8 * 2**30
    check_reconstruct_memory(12, 1080, 1920, "big.npz", scale=scale)  # fits once resized


def test_reconstruct_refuses_before_allocating(monkeypatch):
    """A 12-camera 1080x1920 pair made of broadcast views (a few bytes): the model's entry refuses it."""
    from drivingscene.methods.feedforward import reconstruct

    small = make_pair(12, 8, 8, with_gt=False)
    images = np.broadcast_to(np.zeros((1, 1, 1, 1, 3), np.uint8), (2, 12, 1080, 1920, 3))
    pair = FramePair(**{**small.__dict__, "images": images})
    monkeypatch.setenv(MEMORY_LIMIT_ENV, "4G")
    with pytest.raises(InputError, match=r"^<pair>: images: 12 cameras at 1080x1920 need about .* 4.0 GiB available"):
        reconstruct(None, pair)


def test_refine_refuses_before_allocating(monkeypatch):
    """Refinement from the library (the viewer's Refine button) checks its larger estimate too."""
    from drivingscene.methods.oracle import oracle_reconstruction
    from drivingscene.methods.refine import refine

    pair = make_pair(6, 16, 24)
    recon = oracle_reconstruction(pair)
    monkeypatch.setenv(
        MEMORY_LIMIT_ENV, "272000000"
    )  # bytes: enough to reconstruct 6 x 16x24 (~257 MiB), not to refine (~263 MiB)
    check_reconstruct_memory(6, 16, 24, "pair")
    with pytest.raises(InputError, match=r"^refine: images: 6 cameras at 16x24 need about .* to reconstruct and refine"):
        refine(None, pair, recon)


def test_cli_refuses_from_the_header_alone(tmp_path, monkeypatch, capsys):
    """The command reads the images' declared shape and refuses before loading the file."""
    from drivingscene.cli import main

    scene = _forged_scene(tmp_path / "big.npz", (2, 12, 1080, 1920, 3), make_pair(12, 8, 8, with_gt=False))
    monkeypatch.setenv(MEMORY_LIMIT_ENV, "8G")
    assert main(["reconstruct", str(scene), "-o", str(tmp_path / "r.npz")]) != 0
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert f"{scene}: images: 12 cameras at 1080x1920 need about" in err and "--scale" in err


def test_cli_scale_auto_downscales(tmp_path, monkeypatch, capsys):
    from drivingscene.cli import main
    from drivingscene.gaussians.recon import load_reconstruction

    scene = save_frame_pair(make_pair(2, 48, 64, with_gt=False), tmp_path / "s.npz")
    # room for a quarter of the pixels, and the file's 37 KiB of arrays
    monkeypatch.setenv(MEMORY_LIMIT_ENV, str(reconstruct_bytes(2, 24, 32) + 64 * 1024))
    with pytest.raises(InputError, match="--scale 0.5"):
        check_reconstruct_memory(2, 48, 64, "s.npz", flag="--scale")
    out = tmp_path / "r.npz"
    assert main(["reconstruct", str(scene), "-o", str(out), "--scale", "auto", "--threads", "1"]) == 0
    assert load_reconstruction(out).image_size == (24, 32)


def test_huge_declared_shape_refused(tmp_path):
    scene = _forged_scene(tmp_path / "huge.npz", (2, 6, 100000, 100000, 3), make_pair(6, 8, 8, with_gt=False))
    with pytest.raises(InputError, match=r"huge.npz: images: expected arrays that fit in the .* found shape \[2, 6, 100000"):
        load_frame_pair(scene)


def test_large_real_arrays_refused_under_a_limit(tmp_path, monkeypatch):
    scene = save_frame_pair(make_pair(2, 64, 64, with_gt=False), tmp_path / "s.npz")
    monkeypatch.setenv(MEMORY_LIMIT_ENV, "1K")
    with pytest.raises(InputError, match="images: expected arrays that fit in the 0.00 GiB"):
        load_frame_pair(scene)


def test_huge_declared_shape_allocates_nothing(tmp_path):
    """Under a 3 GiB address-space limit, loading the terabyte scene still ends in the one-line refusal."""
    scene = _forged_scene(tmp_path / "huge.npz", (2, 6, 100000, 100000, 3), make_pair(6, 8, 8, with_gt=False))
    code = textwrap.dedent(
        f"""
        import resource
        from drivingscene.data.npz import load_npz
        from drivingscene.errors import InputError
        resource.setrlimit(resource.RLIMIT_AS, (3 * 2**30, 3 * 2**30))
        try:
            load_npz({str(scene)!r})
        except InputError as e:
            print("REFUSED", e)
        """
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert "REFUSED" in result.stdout and "images" in result.stdout


def _with_zero_member(path: Path, pair: FramePair, key: str, shape: tuple[int, ...]) -> Path:
    """``pair`` saved, with member ``key`` replaced or added: ``shape`` uint8 of zeros, streamed
    into the archive (deflated to a few hundred KB) without holding it in memory."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, value in pair.to_arrays().items():
            if name != key:
                buf = io.BytesIO()
                np.lib.format.write_array(buf, np.asarray(value), allow_pickle=False)
                zf.writestr(f"{name}.npy", buf.getvalue())
        with zf.open(f"{key}.npy", "w", force_zip64=True) as f:
            header = io.BytesIO()
            np.lib.format.write_array_header_1_0(header, {"descr": "|u1", "fortran_order": False, "shape": shape})
            f.write(header.getvalue())
            chunk = bytes(2**20)
            for _ in range(int(np.prod(shape)) // len(chunk)):
                f.write(chunk)
    return path


def _peak_bytes(fn) -> int:
    import tracemalloc

    tracemalloc.start()
    try:
        fn()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


BOMB = (256, 2**20)  # 256 MiB of zeros: a few hundred KB in the archive


def test_an_unknown_member_is_reported_and_never_inflated(tmp_path, capsys):
    from drivingscene.cli import main

    pair = make_pair(2, 16, 24, with_gt=False)
    scene = _with_zero_member(tmp_path / "bomb.npz", pair, "junk", BOMB)
    assert scene.stat().st_size < 2**20
    assert _peak_bytes(lambda: load_frame_pair(scene)) < 32 * 2**20  # the member alone is 256 MiB
    assert main(["validate", str(scene)]) == 0
    captured = capsys.readouterr()
    assert captured.out.strip() == f"{scene}: valid"
    assert (
        captured.err.strip()
        == f"{scene}: warning: junk: not part of the format, never read (declares uint8 [256, 1048576], 0.25 GiB)"
    )
    assert main(["info", str(scene)]) == 0
    assert "unknown     junk: not part of the format" in capsys.readouterr().out


def test_a_member_whose_header_disagrees_is_refused_before_it_is_inflated(tmp_path, capsys):
    from drivingscene.cli import main
    from drivingscene.errors import SceneFormatError

    pair = make_pair(2, 16, 24, with_gt=False)
    scene = _with_zero_member(tmp_path / "images.npz", pair, "images", (2, 3, 1024, 21846, 3))  # 3 cameras, not 2: 400 MB
    with pytest.raises(
        SceneFormatError,
        match=r"images: expected shape \[2, V=2, H=1024, W=21846, 3\] \(RGB at the two keyframes\), found uint8 \[2, 3,",
    ) as info:
        _peak_bytes(lambda: load_frame_pair(scene))
    assert "\n" not in str(info.value)
    peak = _peak_bytes(lambda: main(["validate", str(scene)]))
    assert peak < 32 * 2**20 and "images: expected shape [2, V=2" in capsys.readouterr().err


def test_the_address_space_limit_counts(tmp_path):
    """Under ``ulimit -v`` a scene that fits in the machine's memory but not in the process's
    address space is refused in one line, not by numpy's MemoryError mid-load."""
    scene = _forged_scene(tmp_path / "gig.npz", (2, 6, 4096, 8192, 3), make_pair(6, 8, 8, with_gt=False))  # 1.1 GiB declared
    code = textwrap.dedent(
        f"""
        import resource
        from drivingscene.data.frame_pair import load_frame_pair
        from drivingscene.errors import InputError
        with open("/proc/self/status") as f:
            used = next(int(line.split()[1]) for line in f if line.startswith("VmSize:")) * 1024
        resource.setrlimit(resource.RLIMIT_AS, (used + 2**29, used + 2**29))  # half a GiB of room
        try:
            load_frame_pair({str(scene)!r})
        except InputError as e:
            print("REFUSED", e)
        """
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert "REFUSED" in result.stdout and "gig.npz: images: expected arrays that fit in the 0." in result.stdout
