"""``drivingscene synth``: one pair, a dataset with resume, previews and the one-line error contract."""

from __future__ import annotations

import json

import numpy as np
import pytest

from drivingscene.cli import main
from drivingscene.data import load_frame_pair, validate_frame_pair_file

pytestmark = pytest.mark.gl

TINY = ["--res", "32x56", "--supersample", "2"]


def test_single_pair_is_valid_and_reproducible(tmp_path, capsys):
    a, b = tmp_path / "a.npz", tmp_path / "b.npz"
    assert main(["synth", "--seed", "200004", "--out", str(a), *TINY]) == 0
    assert main(["synth", "--seed", "200004", "--out", str(b), *TINY]) == 0
    assert validate_frame_pair_file(a) == []
    assert a.read_bytes() == b.read_bytes()
    pair = load_frame_pair(a)
    assert pair.image_size == (32, 56) and pair.num_eval == 1 and pair.gt_flow is not None
    assert f"{a}: seed 200004" in capsys.readouterr().out


def test_preset_and_flags_reach_the_file(tmp_path):
    out = tmp_path / "x.npz"
    assert (
        main(
            [
                "synth",
                "--seed",
                "7",
                "--out",
                str(out),
                *TINY,
                "--preset",
                "long_gap",
                "--num-eval",
                "3",
                "--blackout-camera",
                "CAM_BACK",
            ]
        )
        == 0
    )
    pair = load_frame_pair(out)
    assert pair.duration == pytest.approx(1.0) and pair.num_eval == 3
    assert not pair.images[:, pair.camera_names.index("CAM_BACK")].any()


def test_preview_images(tmp_path):
    assert main(["synth", "--seed", "200004", "--out", str(tmp_path / "p.npz"), *TINY, "--preview", str(tmp_path)]) == 0
    assert (tmp_path / "synth_contact_sheet.png").stat().st_size > 1000
    assert (tmp_path / "synth_ground_truth.png").stat().st_size > 1000
    out = tmp_path / "r.npz"
    assert (
        main(
            [
                "synth",
                "--seed",
                "1",
                "--out",
                str(out),
                *TINY,
                "--rig",
                "random",
                "--ego-body",
                "1",
                "--preview",
                str(tmp_path),
                "--preview-name",
                "rand",
            ]
        )
        == 0
    )
    assert (tmp_path / "rand_contact_sheet.png").stat().st_size > 1000  # another rig: cameras by yaw
    assert (tmp_path / "rand_ground_truth.png").stat().st_size > 1000  # first, middle and last camera


def test_dataset_resume_after_interruption(tmp_path, monkeypatch, capsys):
    import drivingscene.synth.generate as generate_module

    out = tmp_path / "ds"
    real = generate_module.generate_pair
    calls = []

    def interrupted(config, seed, renderer=None):
        calls.append(seed)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(config, seed, renderer)

    monkeypatch.setattr(generate_module, "generate_pair", interrupted)
    args = ["synth", "--split", "val", "--count", "3", "--out", str(out), *TINY, "--no-progress"]
    assert main(args) == 130
    assert sorted(p.name for p in out.glob("*.npz")) == ["pair_100000.npz"]
    first = out / "pair_100000.npz"
    stamp = first.stat().st_mtime_ns
    (out / ".pair_100001.npz.abc123.tmp").write_bytes(b"half a file")  # what a killed run leaves
    monkeypatch.setattr(generate_module, "generate_pair", real)
    assert main(args) == 0
    assert "2 pair(s) written, 1 already present" in capsys.readouterr().out
    assert sorted(p.name for p in out.iterdir()) == ["manifest.json", "pair_100000.npz", "pair_100001.npz", "pair_100002.npz"]
    assert first.stat().st_mtime_ns == stamp
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["split"] == "val" and manifest["seeds"] == [100000, 100001, 100002]
    assert manifest["config"]["height"] == 32 and manifest["config"]["supersample"] == 2
    single = tmp_path / "single.npz"
    assert main(["synth", "--seed", "100001", "--out", str(single), *TINY]) == 0
    assert single.read_bytes() == (out / "pair_100001.npz").read_bytes()


def test_dataset_refuses_a_folder_made_with_other_flags(tmp_path, capsys):
    out = tmp_path / "ds"
    assert main(["synth", "--split", "test", "--count", "1", "--out", str(out), *TINY, "--no-progress"]) == 0
    capsys.readouterr()
    assert main(["synth", "--split", "test", "--count", "2", "--out", str(out), *TINY, "--preset", "noisy"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("drivingscene synth: error: --out:") and "noise_std" in err and "\n" not in err
    assert "--force" in err


def test_dataset_force_makes_the_pairs_anew(tmp_path, capsys):
    out = tmp_path / "ds"
    base = ["synth", "--split", "test", "--out", str(out), *TINY, "--no-progress"]
    assert main([*base, "--count", "2"]) == 0
    first = (out / "pair_200000.npz").read_bytes()
    capsys.readouterr()
    # the same flags: made again, byte for byte the same (the generator is deterministic)
    assert main([*base, "--count", "1", "--force"]) == 0
    assert "1 pair(s) written, 0 already present" in capsys.readouterr().out
    assert (out / "pair_200000.npz").read_bytes() == first
    # other flags, leaving one of the folder's two pairs made the old way: refused, nothing touched
    assert main([*base, "--count", "1", "--preset", "noisy", "--force"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("drivingscene synth: error: --out:") and "200001" in err and "\n" not in err
    assert json.loads((out / "manifest.json").read_text())["config"]["noise_std"] == 0.0
    # other flags covering every pair: all made anew, the manifest says how
    assert main([*base, "--count", "2", "--preset", "noisy", "--force"]) == 0
    assert "2 pair(s) written, 0 already present" in capsys.readouterr().out
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["config"]["noise_std"] == 0.03 and manifest["seeds"] == [200000, 200001]
    assert (out / "pair_200000.npz").read_bytes() != first


@pytest.mark.parametrize(
    "argv, flag",
    [
        (["--seed", "1", "--out", "x.npz", "--res", "0x5"], "--res"),
        (["--seed", "1", "--out", "x.npz", "--res", "abc"], "--res"),
        (["--seed", "1", "--out", "x.npz", "--preset", "hard"], "--preset"),
        (["--seed", "1", "--out", "x.npz", "--blackout-camera", "CAM_TOP"], "--blackout-camera"),
        (["--seed", "1", "--out", "x.npz", "--ego-speed", "-4"], "--ego-speed"),
        (["--seed", "1", "--out", "x.npz", "--object-speed-scale", "fast"], "--object-speed-scale"),
        (["--seed", "1", "--out", "x.npz", "--count", "5"], "--count"),
        (["--seed", "-1", "--out", "x.npz"], "--seed"),
        (["--seed", "1", "--out", "x.png"], "--out"),
        (["--split", "dev", "--count", "2", "--out", "d"], "--split"),
        (["--split", "val", "--count", "0", "--out", "d"], "--count"),
        (["--split", "val", "--out", "d"], "--count"),
        (["--out", "d"], "--seed/--split"),
        (["--seed", "1", "--out", "x.npz", "--rig", "fisheye"], "--rig"),
        (["--seed", "1", "--out", "x.npz", "--scene-style", "desert"], "--scene-style"),
        (["--seed", "1", "--out", "x.npz", "--lighting", "night"], "--lighting"),
        (["--seed", "1", "--out", "x.npz", "--photometric", "1.5"], "--photometric"),
        (["--seed", "1", "--out", "x.npz", "--photometric", "strong"], "--photometric"),
        (["--seed", "1", "--out", "x.npz", "--ego-body", "-0.1"], "--ego-body"),
        (["--seed", "1", "--out", "x.npz", "--ego-body", "nan"], "--ego-body"),
        (["--seed", "1", "--out", "x.npz", "--capture-spread", "0.5"], "--capture-spread"),
        (["--seed", "1", "--out", "x.npz", "--randomise-motion", "maybe"], "--randomise-motion"),
        (["--seed", "1", "--out", "x.npz", "--rig", "random", "--blackout-camera", "CAM_7"], "--blackout-camera"),
        (["--seed", "1", "--out", "x.npz", "--rig", "ddad", "--blackout-camera", "CAM_FRONT"], "--blackout-camera"),
        (["--seed", "1", "--out", "x.npz", "--rig", "ddad", "--blackout-camera", "6"], "--blackout-camera"),
        (["--seed", "1", "--out", "x.npz", "--preset", "blackout", "--rig", "ddad"], "--blackout-camera"),
        (["--seed", "1", "--out", "x.npz", "--preview", "p", "--preview-name", "a/b"], "--preview-name"),
    ],
)
def test_bad_arguments_are_one_line_errors(argv, flag, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["synth", *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"drivingscene synth: error: {flag}") and "\n" not in err
    assert "Traceback" not in err
    assert not list(tmp_path.iterdir())  # nothing written


def test_list_presets(capsys):
    assert main(["synth", "--list-presets"]) == 0
    out = capsys.readouterr().out
    for name in (
        "default",
        "easy",
        "fast_ego",
        "fast_objects",
        "crowded",
        "long_gap",
        "low_texture",
        "exposure",
        "noisy",
        "blackout",
        "randomised",
    ):
        assert any(line.startswith(f"{name} ") for line in out.splitlines())
    line = next(line for line in out.splitlines() if line.startswith("randomised "))
    assert "--rig random" in line and "--ego-body 0.6" in line and "--randomise-motion True" in line


def test_randomised_flags_reach_the_file(tmp_path):
    out = tmp_path / "r.npz"
    args = ["synth", "--seed", "200004", "--out", str(out), *TINY, "--preset", "randomised", "--ego-body", "1"]
    assert main([*args, "--randomise-motion", "off", "--capture-spread", "0.02", "--blackout-camera", "none"]) == 0
    pair = load_frame_pair(out)
    assert 5 <= pair.num_views <= 8 and pair.camera_names[0] == "CAM_0"
    assert pair.valid_mask is not None and not pair.valid_mask.all(axis=(1, 2)).all()
    assert pair.duration == pytest.approx(0.5)  # --randomise-motion off: the preset's gap
    assert np.ptp(pair.camera_timestamps[0]) <= 0.02
    again = tmp_path / "again.npz"
    assert (
        main(
            [
                "synth",
                "--seed",
                "200004",
                "--out",
                str(again),
                *TINY,
                "--preset",
                "randomised",
                "--ego-body",
                "1",
                "--randomise-motion",
                "off",
                "--capture-spread",
                "0.02",
            ]
        )
        == 0
    )
    assert again.read_bytes() == out.read_bytes()


def test_dataset_written_before_the_randomisation_knobs_resumes(tmp_path, capsys):
    out = tmp_path / "ds"
    assert main(["synth", "--split", "test", "--count", "1", "--out", str(out), *TINY, "--no-progress"]) == 0
    manifest = json.loads((out / "manifest.json").read_text())
    for key in ("rig", "scene_style", "lighting", "photometric", "ego_body", "capture_spread", "randomise_motion"):
        del manifest["config"][key]  # as an older version wrote it
    (out / "manifest.json").write_text(json.dumps(manifest))
    assert main(["synth", "--split", "test", "--count", "2", "--out", str(out), *TINY, "--no-progress"]) == 0
    assert "1 pair(s) written, 1 already present" in capsys.readouterr().out
    assert main(["synth", "--split", "test", "--count", "2", "--out", str(out), *TINY, "--rig", "ddad"]) == 2
    assert "rig='nuscenes' there" in capsys.readouterr().err
