"""`drivingscene bench choices` on a tiny model and one procedural pair; its variant parser."""

from __future__ import annotations

import pytest

from drivingscene.bench.choices import parse_variant
from drivingscene.cli import main
from drivingscene.data import save_frame_pair
from drivingscene.errors import InputError
from tests.eval.test_bench_results import tiny_weights  # noqa: F401  (fixture)


def test_variants_parse_and_bad_ones_are_named():
    v = parse_variant("blend=layers,carve=same_time,search=off")
    assert (v.blend, v.carve, v.search) == ("layers", "same_time", False)
    assert parse_variant("").blend == "all"
    with pytest.raises(InputError, match="'carve=maybe'"):
        parse_variant("carve=maybe")


def test_bench_choices_report(synth_pair, tiny_weights, tmp_path):  # noqa: F811
    data = tmp_path / "val"
    data.mkdir()
    save_frame_pair(synth_pair, data / "pair_100000.npz")
    out = tmp_path / "choices.md"
    args = ["bench", "choices", "--data", str(data), "--count", "1", "--weights", str(tiny_weights), "--out", str(out)]
    assert main([*args, "--variant", "blend=all", "--variant", "blend=layers,carve=all"]) == 0
    text = out.read_text()
    assert "| blend=all |" in text and "| blend=layers,carve=all |" in text and "input views PSNR" in text
    assert main(["bench", "choices", "--data", str(data), "--variant", "blend=nope"]) == 2
