"""`drivingscene bench real` end to end on a small pair with LiDAR-like depth, a valid_mask and a
real in-between frame, with a tiny random model; and the "loses to a trivial baseline" rule."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np

from drivingscene.bench.real_common import BLEND, COPY, FULL, NEAREST, ROAD, WITHOUT_SKY
from drivingscene.bench.real_markdown import losers
from drivingscene.cli import main
from drivingscene.data import save_frame_pair
from tests.eval.test_bench_results import tiny_weights  # noqa: F401  (fixture)


def _real_like(pair):
    """The procedural pair made to look like an imported real one: sparse depth, a masked hood."""
    rng = np.random.default_rng(0)
    sparse = np.where(rng.uniform(size=pair.gt_depth.shape) < 0.1, pair.gt_depth, 0).astype(np.float32)
    mask = np.ones((pair.num_views, *pair.image_size), bool)
    mask[:, -6:] = False
    return replace(pair, gt_depth=sparse, gt_flow=None, gt_scene_flow=None, gt_dynamic=None, eval_dynamic=None, valid_mask=mask)


def test_bench_real_report(synth_pair, tiny_weights, tmp_path):  # noqa: F811
    scene = tmp_path / "scene.npz"
    save_frame_pair(_real_like(synth_pair), scene)
    md, js, figs = tmp_path / "real.md", tmp_path / "real.json", tmp_path / "figs"
    args = ["bench", "real", str(scene), "--names", "tiny", "--weights", str(tiny_weights), "--repeats", "1"]
    assert main([*args, "--lpips", "stlpips", "--out", str(md), "--json", str(js), "--images", str(figs)]) == 0
    text = md.read_text()
    for needle in (
        "## Summary",
        "### tiny",
        COPY,
        BLEND,
        "median-scaled",
        "re-rendered",
        "](figs/tiny.png)",
        "not committed",
        ROAD,
        NEAREST,
        "## Depth next to trivial baselines",
    ):
        assert needle in text
    scores = json.loads(js.read_text())["tiny"]
    assert set(scores["novel"]) == {FULL, "DrivingScene, static-only (no residual flow)", COPY, BLEND}
    v = synth_pair.num_views
    assert all(len(scores["novel"][m]["psnr"]) == v for m in scores["novel"])
    assert all(math.isfinite(x) for x in scores["depth"]["metric"]["abs_rel"])
    assert set(scores["depth_baselines"]) == {ROAD, NEAREST}
    assert all(math.isfinite(x) for b in scores["depth_baselines"].values() for x in b["metric"]["abs_rel"])
    assert (figs / "tiny.png").stat().st_size > 1000
    # what a larger window shows: the rig views at 1, 2 and 4 times the input, and the overview
    assert "## Views larger than the input" in text and "](figs/tiny_overview.png)" in text
    assert set(scores["magnified"]) == {"1", "2", "4"}
    assert WITHOUT_SKY in scores["keyframes"] and WITHOUT_SKY in text  # the re-render without its sky pixels
    for k in ("1", "2", "4"):
        m = scores["magnified"][k]
        assert math.isfinite(m["psnr_vs_bicubic"]) and math.isfinite(m["psnr_area_down"]) and 0.0 <= m["holes"] <= 1.0
    assert (figs / "tiny_overview.png").stat().st_size > 1000


def test_bench_real_refuses_bad_arguments(tmp_path, capsys):
    code = main(["bench", "real", str(tmp_path / "missing.npz"), "--repeats", "1"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "missing.npz" in err and "\n" not in err


def test_losers_are_methods_below_the_better_baseline():
    novel = {
        "a": {"psnr": [20.0, 22.0]},
        "b": {"psnr": [18.0, 18.0]},
        COPY: {"psnr": [17.0, 17.0]},
        BLEND: {"psnr": [19.0, 19.5]},
    }
    assert losers(novel) == {"b"}
    assert losers({"a": {"psnr": [1.0]}}) == set()  # no baseline, nobody loses


def test_bench_real_scores_refined_reconstructions(synth_pair, tiny_weights, tmp_path):  # noqa: F811
    from drivingscene.bench.real_refine import lidar_halves, method_name

    scene = tmp_path / "scene.npz"
    save_frame_pair(_real_like(synth_pair), scene)
    md, js = tmp_path / "real.md", tmp_path / "real.json"
    args = [
        "bench",
        "real",
        str(scene),
        "--names",
        "tiny",
        "--weights",
        str(tiny_weights),
        "--repeats",
        "1",
        "--lpips",
        "stlpips",
    ]
    assert main([*args, "--refine", "2", "--lidar", "--out", str(md), "--json", str(js)]) == 0
    text = md.read_text()
    assert "## Test-time refinement" in text and "--refine 2 --lidar" in text and "## Depth next to trivial baselines" in text
    scores = json.loads(js.read_text())["tiny"]
    plain, lidar = method_name(2.0), method_name(2.0, lidar=True)
    assert {plain, lidar} <= set(scores["novel"]) and {plain, lidar} <= set(scores["refine"])
    assert scores["refine"][plain]["budget_s"] == 2.0
    assert all(math.isfinite(x) for x in scores["depths"][lidar]["metric"]["abs_rel"])
    # the steps in another blend: a row of its own, named and in the recorded command
    assert main([*args, "--refine", "1", "--adapt", "0", "--blend", "all", "--out", str(md), "--json", str(js), "--force"]) == 0
    assert "--refine 1 --adapt 0 --blend all" in md.read_text()
    assert method_name(1.0, adapt=0, blend="all") in json.loads(js.read_text())["tiny"]["refine"]
    for flag, value in (("--blend", "all"), ("--adapt-share", "0.5"), ("--adapt-scale", "0.5")):  # only with --refine
        assert main([*args, flag, value, "--out", str(md), "--force"]) == 2
    fit, held = lidar_halves(_real_like(synth_pair).gt_depth)
    assert not ((fit > 0) & (held > 0)).any() and np.array_equal(np.maximum(fit, held), _real_like(synth_pair).gt_depth)


def test_every_refinement_setting_given_names_its_row():
    from drivingscene.bench.real_refine import method_name

    names = {
        method_name(30.0),
        method_name(30.0, adapt=5),
        method_name(30.0, blend="all"),
        method_name(30.0, adapt_share=0.67),
        method_name(30.0, adapt_scale=1.0),
        method_name(30.0, adapt_share=0.67, adapt_scale=1.0),
    }
    assert len(names) == 6  # rows of different settings never share a name (nor overwrite in the JSON)
    assert "0.67 of the budget" in method_name(30.0, adapt_share=0.67) and "losses at 1x" in method_name(30.0, adapt_scale=1.0)


def test_identical_images_score_the_ceiling_not_infinity():
    """A keyframe blend where nothing moved equals the target: its cameras score PSNR_CEILING, so a
    mean over cameras (the summary's) stays finite and comparable; others keep their own figure."""
    import torch

    from drivingscene.bench.real import image_scores
    from drivingscene.bench.real_common import PSNR_CEILING

    target = torch.rand(1, 2, 16, 24, 3, generator=torch.Generator().manual_seed(0))
    pred = target.clone()
    pred[:, 1] = (pred[:, 1] + 0.1).clamp(0, 1)  # the second camera off by about 0.1
    scores = image_scores(pred, target, None, None, num_views=2)
    assert scores["psnr"][0] == PSNR_CEILING
    assert math.isfinite(scores["psnr"][1]) and 15.0 < scores["psnr"][1] < 25.0


def test_magnified_rows_stop_at_what_a_window_shows():
    """A camera image already as wide as a window is scored at 1x only (its 4x would not fit in
    memory on the CPU); the table marks the missing magnifications instead of failing."""
    from drivingscene.bench.real import magnifications_for
    from drivingscene.bench.real_common import WINDOW_WIDTH, SceneScores
    from drivingscene.bench.real_markdown import magnified_table

    assert magnifications_for(320) == (1, 2, 4)
    assert magnifications_for(640) == (1, 2)
    assert magnifications_for(WINDOW_WIDTH + 1) == (1,)
    s = SceneScores("big", {}, magnified={1: {"psnr_vs_bicubic": 30.0, "psnr_area_down": 30.0, "holes": 0.0}})
    table = magnified_table([s])
    assert "| big | 30.00 | – | – | – | – | – |" in table
