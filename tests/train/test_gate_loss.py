"""The matching gate's target: open where matching alone is nearer the truth."""

from __future__ import annotations

from types import SimpleNamespace

import torch

from drivingscene.train.stages import gate_loss


def _out(mono: float, match: float, gate: float, informative: bool = True):
    shape = (1, 4, 6)
    return SimpleNamespace(
        mono_depths=[torch.full(shape, mono)],
        match_depth=torch.full(shape, match),
        gate=torch.full(shape, gate),
        matching=SimpleNamespace(informative=torch.full((1, 1, 2, 3), informative)),
    )


def test_gate_is_pushed_open_where_matching_is_right_and_shut_where_it_is_wrong():
    gt = torch.full((1, 4, 6), 10.0)
    still = torch.zeros(1, 4, 6, dtype=torch.bool)
    right = gate_loss(_out(mono=4.0, match=9.0, gate=0.9), gt, still)
    assert right < gate_loss(_out(mono=4.0, match=9.0, gate=0.1), gt, still)  # matching right: open is better
    assert gate_loss(_out(mono=9.0, match=4.0, gate=0.1), gt, still) < gate_loss(_out(mono=9.0, match=4.0, gate=0.9), gt, still)


def test_no_target_where_no_source_is_informative_or_no_ground_truth():
    still = torch.zeros(1, 4, 6, dtype=torch.bool)
    assert gate_loss(_out(4.0, 9.0, 0.0, informative=False), torch.full((1, 4, 6), 10.0), still) == 0
    assert gate_loss(_out(4.0, 9.0, 0.0), torch.zeros(1, 4, 6), still) == 0
