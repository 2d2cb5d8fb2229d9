"""`drivingscene bench looks`: depth under global tone changes, on a tiny model and one procedural pair."""

from __future__ import annotations

import numpy as np
import pytest

from drivingscene.bench.looks import parse_tone, toned
from drivingscene.cli import main
from drivingscene.errors import InputError
from tests.eval.test_bench_results import tiny_weights  # noqa: F401  (fixture)


def test_tones_parse_apply_and_bad_ones_are_named():
    assert parse_tone("gamma=1.6") == ("gamma", 1.6) and parse_tone("gain=0.5") == ("gain", 0.5)
    for bad in ("gamma", "gamma=x", "gamma=0", "tint=1", "gain=nan"):
        with pytest.raises(InputError, match=f"found '{bad}'"):
            parse_tone(bad)
    images = np.array([[0, 64, 128, 255]], np.uint8)
    assert np.array_equal(toned(images, "gamma", 1.0), images)
    assert np.array_equal(toned(images, "gain", 2.0), [[0, 128, 255, 255]])  # clipped
    darker = toned(images, "gamma", 2.0)
    assert darker[0, 0] == 0 and darker[0, 3] == 255 and (darker[0, 1:3] < images[0, 1:3]).all()


def test_bench_looks_report(synth_pair_folder, tiny_weights, tmp_path):  # noqa: F811
    data = synth_pair_folder
    out = tmp_path / "looks.md"
    args = ["bench", "looks", "--data", str(data), "--count", "1", "--weights", str(tiny_weights), "--out", str(out)]
    assert main([*args, "--tones", "gamma=1", "gain=0.5"]) == 0
    rows = [line for line in out.read_text().splitlines() if line.startswith(f"| {data} (1) |")]
    assert [r.split(" | ")[2] for r in rows] == ["gamma 1", "gain 0.5"]
    for row in rows:
        values = [float(x) for x in row.strip("| ").split(" | ")[3:]]
        assert len(values) == 4 and all(np.isfinite(values)) and all(v >= 0 for v in values)
    assert main(["bench", "looks", "--data", str(data), "--tones", "gamma=-1"]) == 2
    assert main(["bench", "looks", "--data", str(tmp_path / "missing")]) == 2
