"""`drivingscene bench results` end to end on a real procedural pair with a tiny random model."""

from __future__ import annotations

import json

import cv2
import pytest
import torch
from safetensors.torch import save_file

from drivingscene.cli import main
from drivingscene.data import save_frame_pair
from drivingscene.models import DrivingSceneModel, ModelConfig
from drivingscene.models.depth import DepthConfig
from drivingscene.models.residual_flow import FlowConfig


@pytest.fixture
def tiny_weights(tmp_path):
    torch.manual_seed(0)
    config = ModelConfig(
        depth=DepthConfig(width=8, decoder_channels=(8, 8, 16, 16, 32)), flow=FlowConfig(channels=(8, 8, 16, 16), hidden=8)
    )
    path = tmp_path / "tiny.safetensors"
    save_file({k: v.contiguous() for k, v in DrivingSceneModel(config).state_dict().items()}, str(path))
    path.with_suffix(".json").write_text(json.dumps({"model": config.to_dict()}))
    return path


@pytest.mark.gl
def test_results_report_json_and_figure(synth_pair, tiny_weights, tmp_path):
    data = tmp_path / "test"
    data.mkdir()
    save_frame_pair(synth_pair, data / "pair_200000.npz")
    md, js, png = tmp_path / "results.md", tmp_path / "scores.json", tmp_path / "results.png"
    args = ["bench", "results", "--data", str(data), "--count", "1", "--weights", str(tiny_weights)]
    args += [
        "--joint-weights",
        str(tiny_weights),
        "--extra",
        f"another={tiny_weights}",
        "--diagnostics",
        "--lpips",
        "stlpips",
        "--out",
        str(md),
        "--json",
        str(js),
        "--image",
        str(png),
    ]
    notes = tmp_path / "notes.md"
    notes.write_text("## Why it looks like this\n")
    assert main([*args, "--notes", str(notes)]) == 0
    text = md.read_text()
    assert text.endswith("## Why it looks like this\n")
    assert "](results.png)" in text
    methods = [
        "DrivingScene (two-stage)",
        "static-only",
        "single-stage (joint training)",
        "another",
        "oracle (GT depth + scene flow)",
    ]
    methods += ["diagnostic: DrivingScene depth + GT flow", "diagnostic: oracle without scene flow"]
    methods += ["diagnostic: DrivingScene depth + GT flow + 1/4 of R's flow error"]
    methods += ["DrivingScene, R alone (no search)", "diagnostic: the search without R"]
    methods += ["DrivingScene, D's depth unmatched (no matching at inference)", "DrivingScene, no object tracking"]
    methods += ["baseline: copy the nearest keyframe", "baseline: blend the two keyframes"]
    for heading in ("all pixels", "dynamic pixels", "Depth at the keyframes", "end-point error", "ST-LPIPS"):
        assert heading in text
    assert all(m in text for m in methods)
    scores = json.loads(js.read_text())
    assert "Full model vs static-only on dynamic pixels" in text and "lowers the dynamic-pixel flow error" in text
    assert "AbsRel, moving objects" in text
    assert "R alone (no search) vs static-only on dynamic pixels" in text and "R's residual alone lowers" in text
    assert len(scores) == 14 and all(len(rows) == 1 for rows in scores.values())
    # a method below the better trivial baseline (all pixels) is said so in bold, and only such a
    # method; the oracle is above it
    trivial = max(scores[b][0]["psnr"] for b in ("baseline: copy the nearest keyframe", "baseline: blend the two keyframes"))
    all_pixels = text.split("novel views, all pixels")[1].split("###")[0]
    for name, rows in scores.items():
        if not name.startswith("baseline"):
            assert (f"**{name} — loses to a trivial baseline**" in all_pixels) == (rows[0]["psnr"] < trivial), name
    assert "**oracle (GT depth + scene flow) — loses" not in text
    assert "Full model vs the better trivial baseline" in text
    assert "baseline: blend" not in text.split("Depth at the keyframes")[1]  # baselines only in novel-view tables
    oracle = scores["oracle (GT depth + scene flow)"][0]
    assert oracle["depth_abs_rel"] < 1e-6 and oracle["psnr_dyn"] > scores["static-only (no residual flow)"][0]["psnr_dyn"]
    assert oracle["psnr_dyn"] > scores["diagnostic: oracle without scene flow"][0]["psnr_dyn"]
    with_gt = scores["diagnostic: DrivingScene depth + GT flow"][0]
    full = scores["DrivingScene (two-stage)"][0]
    assert with_gt["epe_dyn_total"] < 0.5 < full["epe_dyn_total"]  # the ground truth itself, up to bounding
    # A quarter of R's own error (R alone: the search is not part of the diagnostic).
    quarter = scores["diagnostic: DrivingScene depth + GT flow + 1/4 of R's flow error"][0]
    r_alone = scores["DrivingScene, R alone (no search)"][0]
    assert 0.2 * r_alone["epe_dyn_total"] < quarter["epe_dyn_total"] < 0.3 * r_alone["epe_dyn_total"]
    image = cv2.imread(str(png))
    height, width = synth_pair.image_size
    assert image.shape[0] > 2 * height and 10 * width > image.shape[1] > 8 * width  # 2 rows; frame + 7 methods (no diagnostics)


def test_checks_compare_pair_by_pair_with_a_sign_test():
    from drivingscene.bench.results import FULL, R_ALONE, STATIC, checks, sign_test

    assert sign_test(6, 6) == 1 / 64 and sign_test(0, 6) == 1.0 and sign_test(10, 20) > 0.5
    full = [{"psnr_dyn": 20.0, "epe_dyn_rigid": 10.0, "epe_dyn_total": 8.0}] * 6
    lines = checks({FULL: full, STATIC: [{"psnr_dyn": 19.0}] * 6})
    assert "PSNR +1.00 dB on average, higher in 6 of 6 pairs — **holds** (sign test p = 0.016)" in lines[0]
    assert "+2.00 px on average" in lines[1] and "lower in 6 of 6 pairs — **holds**" in lines[1]
    # better on average thanks to one pair: not shown
    mixed = [{"psnr_dyn": 25.0, "epe_dyn_rigid": 5.0, "epe_dyn_total": 4.0}] + [
        {"psnr_dyn": 18.9, "epe_dyn_rigid": 5.0, "epe_dyn_total": 6.0}
    ] * 3
    lines = checks({FULL: mixed, STATIC: [{"psnr_dyn": 19.0}] * 4})
    assert "**not shown**" in lines[0] and "higher in 1 of 4 pairs" in lines[0]
    assert "**does NOT hold**" in lines[1]
    # With R alone scored too, both claims are also stated for it, after the full model's.
    lines = checks({FULL: full, STATIC: [{"psnr_dyn": 19.0}] * 6, R_ALONE: mixed[1:] * 2})
    assert len(lines) == 4 and lines[1].startswith("- R alone (no search) vs static-only") and "higher in 0 of 6" in lines[1]
    assert lines[3].startswith("- R's residual alone lowers") and "**does NOT hold**" in lines[3]


def test_extra_needs_name_and_weights(tmp_path, capsys):
    data = tmp_path / "d"
    data.mkdir()
    assert main(["bench", "results", "--data", str(data), "--extra", "noequals"]) == 2
    assert "--extra: expected NAME=WEIGHTS" in capsys.readouterr().err


def test_missing_notes_file_fails_before_any_work(tmp_path, capsys):
    assert main(["bench", "results", "--data", str(tmp_path), "--notes", str(tmp_path / "nope.md")]) == 2
    assert "nope.md: --notes: expected a readable markdown file" in capsys.readouterr().err


def test_search_settings_parse_into_the_config_and_bad_ones_fail_in_one_line(tmp_path, capsys):
    from drivingscene.bench.search import DEFAULT_SETTINGS, parse_setting

    config = parse_setting("window=7,static_bonus=0.02,use_network=false")
    assert (config.window, config.static_bonus, config.use_network, config.scale_step) == (7, 0.02, False, 0.1)
    assert all(parse_setting(s) for s in DEFAULT_SETTINGS)
    for bad, expected in (("colour=3", "KEY one of"), ("window=x", "expected an integer"), ("window=4", "odd number")):
        assert main(["bench", "search", "--data", str(tmp_path), "--setting", bad]) == 2
        err = capsys.readouterr().err
        assert expected in err and err.count("\n") == 1


@pytest.mark.parametrize("flag", [None, "--no-search", "--no-match", "--match depth"])
def test_inference_benchmark_reports_the_search_and_matching_shares(tiny_weights, tmp_path, flag):
    out = tmp_path / "inference.md"
    args = ["bench", "inference", "--sizes", "48x88", "--runs", "1", "--weights", str(tiny_weights), "--out", str(out)]
    assert main(args + (flag.split() if flag else [])) == 0
    text = out.read_text()
    row = text.splitlines()[-1].split(" | ")
    assert row[0] == "| 48x88"
    assert (float(row[4].split()[0]) > 0) == (flag != "--no-match")  # "matching s (cameras matched again)"
    assert (float(row[6]) > 0) == (flag != "--no-search")  # "of which search s"
    assert float(row[9].split()[0]) > 0  # peak RSS of a fresh process's reconstruction (MiB)
    assert ("--no-search" in text) == (flag == "--no-search")
    assert ("--match off" in text) == (flag == "--no-match") and ("--match depth" in text) == (flag == "--match depth")
    assert "compiled CPU kernels on" in text or "compiled CPU kernels off" in text


def test_inference_benchmark_times_scene_files_too(tiny_weights, tmp_path):
    from drivingscene.data.frame_pair import save_frame_pair
    from tests.factories import make_pair

    scene = save_frame_pair(make_pair(num_views=2, height=24, width=40), tmp_path / "mine.npz")
    out = tmp_path / "inference.md"
    args = ["bench", "inference", "--sizes", "48x88", "--scenes", str(scene), "--runs", "1", "--weights", str(tiny_weights)]
    assert main(args + ["--out", str(out)]) == 0
    rows = [line for line in out.read_text().splitlines() if line.startswith("| ") and "---" not in line][1:]
    assert [r.split(" | ")[0] for r in rows] == ["| 48x88", "| mine.npz (2 × 24x40)"]
    assert f"--scenes {scene}" in out.read_text()
    # scene files alone (a machine without EGL for the procedural pairs, e.g. a GPU machine), and nothing at all
    assert main(args[:2] + ["--sizes"] + args[4:] + ["--out", str(out), "--force"]) == 0
    rows = [line for line in out.read_text().splitlines() if line.startswith("| ") and "---" not in line][1:]
    assert [r.split(" | ")[0] for r in rows] == ["| mine.npz (2 × 24x40)"]
    assert main(["bench", "inference", "--sizes", "--runs", "1"]) == 2


def test_inference_benchmark_profiles_the_operations_of_each_pair(tiny_weights, tmp_path):
    out = tmp_path / "inference.md"
    args = ["bench", "inference", "--sizes", "48x88", "--runs", "1", "--weights", str(tiny_weights), "--profile", "4"]
    assert main(args + ["--out", str(out)]) == 0
    text = out.read_text()
    assert "--profile 4`" in text and "Where the time of 48x88 goes" in text
    table = text[text.index("| operation |") :].splitlines()[2:]
    assert len(table) == 4
    times = [float(line.split(" | ")[2]) for line in table]
    assert times == sorted(times, reverse=True) and times[0] > 0  # the heaviest first, milliseconds per reconstruction
    assert all("::" in line.split(" | ")[0] for line in table)  # aten:: or the compiled kernels' namespace


def test_peak_memory_of_a_spawned_process_does_not_inherit_the_parents():
    """``ru_maxrss`` carries the parent's resident memory at the fork into a spawned process; the
    per-size memory figures of `bench inference` come from such processes."""
    import multiprocessing

    import numpy as np

    from drivingscene.machine import current_rss_bytes, peak_rss_bytes

    ballast = np.ones(400 * 2**20 // 8)  # 400 MiB, touched
    with multiprocessing.get_context("spawn").Pool(1) as pool:
        child_peak = pool.apply(peak_rss_bytes)
    assert current_rss_bytes() > 400 * 2**20 and ballast.sum() > 0
    assert child_peak < current_rss_bytes() - 300 * 2**20


def test_methods_below_the_better_baseline_are_bold():
    """The table logic alone, on made-up scores: all-pixel PSNR against the better baseline (22 dB,
    copy), moving-pixel PSNR against its better baseline (16 dB, blend)."""
    from types import SimpleNamespace

    from drivingscene.bench.results import BLEND, COPY, FULL, STATIC, losing, report

    def rows(*values):
        return [{"psnr": a, "psnr_dyn": d, "ssim": 0.5, "ssim_dyn": 0.4} for a, d in values]

    scores = {
        FULL: rows((25.0, 12.0), (25.0, 12.0)),
        STATIC: rows((20.0, 15.0), (21.0, 15.0)),
        COPY: rows((22.0, 14.0), (22.0, 14.0)),
        BLEND: rows((21.0, 16.0), (21.0, 16.0)),
    }
    assert losing(scores, "psnr") == {STATIC} and losing(scores, "psnr_dyn") == {FULL, STATIC}
    assert losing({FULL: rows((25.0, 12.0))}, "psnr") == set()  # no baseline scored: nothing to lose to
    args = SimpleNamespace(
        data="d", count=2, weights=None, joint_weights=None, extra=[], diagnostics=False, notes=None, image=None
    )
    text = report(scores, {m: [1.0] for m in scores}, "ST-LPIPS (alex)", args, 2)
    all_pixels, dynamic = text.split("### Intermediate-frame novel views, dynamic pixels")
    all_pixels = all_pixels.split("### Intermediate-frame novel views, all pixels")[1]
    assert f"| **{STATIC} — loses to a trivial baseline** | **20.50** | **0.500** | **–** |" in all_pixels
    assert f"| {FULL} | 25.00 |" in all_pixels and f"| {COPY} | 22.00 |" in all_pixels
    dynamic = dynamic.split("### Depth")[0]
    assert f"| **{FULL} — loses to a trivial baseline** | **12.00** | **0.400** | **–** |" in dynamic
    assert f"| {BLEND} | 16.00 |" in dynamic and "baseline: copy" not in text.split("### Depth")[1]
    assert "Full model vs the better trivial baseline (copy the nearest keyframe), all pixels: PSNR +3.00 dB" in text
