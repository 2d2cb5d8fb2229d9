"""`drivingscene bench choices` on a tiny model and one procedural pair; its variant parser."""

from __future__ import annotations

from dataclasses import replace

import pytest

from drivingscene.bench.choices import parse_variant
from drivingscene.cli import main
from drivingscene.data import save_frame_pair
from drivingscene.errors import InputError
from drivingscene.gaussians.timing import DEFAULT_BLEND
from tests.eval.test_bench_results import tiny_weights  # noqa: F401  (fixture)


def test_variants_parse_and_bad_ones_are_named():
    v = parse_variant("blend=layers,carve=same_time,search=off")
    assert (v.blend, v.carve, v.search) == ("layers", "same_time", False)
    assert parse_variant("").blend == DEFAULT_BLEND
    with pytest.raises(InputError, match="'carve=maybe'"):
        parse_variant("carve=maybe")
    with pytest.raises(InputError, match="'bonus=-1'"):
        parse_variant("bonus=-1")
    with pytest.raises(InputError, match="'mtest=median'"):
        parse_variant("mtest=median")


def test_the_merge_of_2026_12_01_is_a_variant_and_off_stays_off():
    from drivingscene.methods.feedforward import InferenceOptions

    old = parse_variant("merge=0.06,mtest=range,mfit=0").options(InferenceOptions()).merge
    assert (old.color_range, old.color_test, old.fit_colors) == (0.06, "range", 0)
    assert parse_variant("merge=off,mfit=2").options(InferenceOptions()).merge is None
    assert parse_variant("mfit=1").options(InferenceOptions()).merge.color_range == InferenceOptions().merge.color_range
    budget = parse_variant("mbudget=0.5").options(InferenceOptions()).merge
    assert (budget.budget, budget.color_range) == (0.5, InferenceOptions().merge.color_range)
    for bad in ("mbudget=0", "mbudget=1.5"):
        with pytest.raises(InputError, match=f"'{bad}'"):
            parse_variant(bad)


def test_sign_test_is_the_exact_binomial_tail():
    from drivingscene.bench.choices import _sign, sign_test

    assert sign_test(10, 0) == pytest.approx(2 / 2**10)
    assert sign_test(5, 5) == 1.0 and sign_test(0, 0) == 1.0
    assert sign_test(15, 5) == pytest.approx(0.0414, abs=1e-4)  # 20 pairs, 15 wins: below 0.05
    assert _sign([2.0, 3.0, float("nan")], [1.0, 4.0, 1.0]) == "1 / 2 (p 1.000)" and _sign([1.0], None) == "–"


def test_variant_options_change_only_what_they_name():
    from drivingscene.methods.feedforward import InferenceOptions

    base = InferenceOptions()
    same = parse_variant("blend=layers").options(base)
    assert same.search == base.search and same.lift == base.lift and same.carve is None
    v = parse_variant("bonus=0.05,photo=on,region=12").options(base)
    assert v.search.static_bonus == 0.05 and v.search.window == base.search.window
    assert v.lift.photometric_check and v.lift.min_dynamic_region == 12
    assert v.lift.dynamic_threshold_px == base.lift.dynamic_threshold_px
    assert parse_variant("search=off,bonus=0.05").options(base).search is None
    assert same.gaussian_head and not parse_variant("head=off").options(base).gaussian_head
    unseen = parse_variant("unseen=static").options(base).search
    assert unseen.unseen_static and replace(unseen, unseen_static=base.search.unseen_static) == base.search
    assert not parse_variant("unseen=search").options(base).search.unseen_static
    with pytest.raises(InputError, match="'unseen=maybe'"):
        parse_variant("unseen=maybe")
    assert parse_variant("unseenpx=1.5").options(base).search.unseen_residual_px == 1.5
    forced = parse_variant("fdisp=0,pmatch=fast").options(base).match
    assert (forced.fallback_dispersion, forced.prior_preset) == (0.0, "fast")
    assert replace(forced, fallback_dispersion=base.match.fallback_dispersion, prior_preset=base.match.prior_preset) == base.match
    assert parse_variant("rig=off").options(base).match == replace(base.match, cross=None)
    assert parse_variant("rig=on").options(base).match == base.match and base.match.cross is not None
    assert parse_variant("replace=off").options(base).match == replace(base.match, replace=False) and base.match.replace
    for bad in ("pmatch=off", "fdisp=-1", "rig=maybe", "replace=maybe"):
        with pytest.raises(InputError, match=f"'{bad}'"):
            parse_variant(bad)
    with pytest.raises(InputError, match="'unseenpx=-1'"):
        parse_variant("unseenpx=-1")
    assert base.objects is not None and parse_variant("").options(base).objects == base.objects  # tracked by default
    assert parse_variant("objects=off").options(base).objects is None
    objects = parse_variant("objects=rigid,osplit=on,omotion=2,odetect=fallback").options(base).objects
    assert (objects.elsewhere, objects.split, objects.min_motion, objects.detect) == ("rigid", True, 2.0, "fallback")
    # the default's choices changed one at a time, the rest kept
    assert parse_variant("omax=0.3,omargin=40").options(base).objects == replace(base.objects, max_motion=0.3, margin_x=40)
    assert parse_variant("oland=0.01").options(base).objects == replace(base.objects, landing=0.01)
    assert parse_variant("mout=0.3").options(base).match == replace(base.match, prior_outlier=0.3)
    assert parse_variant("mout=off").options(base).match == base.match
    assert parse_variant("mout=0.3,mmove=on").options(base).match == replace(base.match, prior_outlier=0.3, refused_motion=True)
    assert parse_variant("oland=off").options(replace(base, objects=replace(base.objects, landing=0.01))).objects == base.objects
    assert not parse_variant("residual=off").options(base).use_residual
    for bad in (
        "objects=maybe",
        "omotion=-1",
        "osplit=maybe",
        "odetect=maybe",
        "omax=0",
        "omargin=-3",
        "oland=-1",
        "mout=0",
        "mmove=maybe",
    ):
        with pytest.raises(InputError, match=f"'{bad}'"):
            parse_variant(bad)


def test_bench_choices_report(synth_pair, synth_pair_folder, tiny_weights, tmp_path):  # noqa: F811
    data = synth_pair_folder
    out = tmp_path / "choices.md"
    args = ["bench", "choices", "--data", str(data), "--count", "1", "--weights", str(tiny_weights), "--out", str(out)]
    assert main([*args, "--variant", "blend=all", "--variant", "blend=layers,carve=all,parallax=on"]) == 0
    text = out.read_text()
    assert "| blend=all |" in text and "| blend=layers,carve=all,parallax=on |" in text and "input views PSNR" in text
    assert main(["bench", "choices", "--data", str(data), "--variant", "blend=nope"]) == 2
    # a first pair without intermediate frames (real keyframe pairs) does not hide the others' scores
    save_frame_pair(
        replace(
            synth_pair,
            eval_images=None,
            eval_timestamps=None,
            eval_ego_to_world=None,
            eval_dynamic=None,
            eval_camera_ego_to_world=None,
            eval_camera_timestamps=None,
        ),
        data / "pair_000000.npz",
    )
    assert main([*args[:5], "2", *args[6:], "--variant", "blend=layers", "--force"]) == 0
    row = next(line for line in out.read_text().splitlines() if line.startswith("| blend=layers |"))
    assert "nan" not in row.split("|")[3]
    one = data / "pair_100000.npz"  # a scene file instead of a folder
    assert (
        main(
            [
                "bench",
                "choices",
                "--data",
                str(one),
                "--weights",
                str(tiny_weights),
                "--out",
                str(out),
                "--variant",
                "blend=layers",
                "--force",
            ]
        )
        == 0
    )
    assert f"### {one} (1 pair; moving pixels in the ground truth:" in out.read_text()
    real = data / "real.npz"  # a real pair: no ground-truth motion, so no moving-pixel score
    save_frame_pair(replace(synth_pair, gt_dynamic=None, eval_dynamic=None), real)
    assert (
        main(
            [
                "bench",
                "choices",
                "--data",
                str(real),
                "--weights",
                str(tiny_weights),
                "--out",
                str(out),
                "--variant",
                "blend=layers",
                "--force",
            ]
        )
        == 0
    )
    text = out.read_text()
    assert f"### {real} (1 pair; no ground-truth motion)" in text
    row = next(line for line in text.splitlines() if line.startswith("| blend=layers |"))
    assert row.split("|")[4].strip() == "n/a" and "nan" not in row
