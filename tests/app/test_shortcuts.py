"""The shortcut table: the key handler and Help read it, so every handled key is listed in Help."""

from __future__ import annotations

import pytest
from drivingscene_view import interaction
from drivingscene_view.shortcuts import SHORTCUTS, combo, find, held_keys
from drivingscene_view.window import KEY_NAMES


def test_every_action_is_in_the_help_table_and_back():
    listed = {s.name for s in SHORTCUTS if not s.held} - {"rig_camera"}  # rig_camera: the digit picks the camera
    assert set(interaction.ACTIONS) == listed
    assert all(s.label and s.text for s in SHORTCUTS)


def test_every_named_key_of_the_window_is_bound():
    bound = {key.split("+")[-1] for s in SHORTCUTS for key in s.keys}
    assert set(KEY_NAMES.values()) <= bound


@pytest.mark.parametrize(
    ("key", "ctrl", "shift", "name"),
    [
        ("o", True, False, "open"),
        ("s", True, False, "save"),
        ("q", True, False, "quit"),
        ("y", True, False, "redo"),
        ("z", True, True, "redo"),
        ("z", True, False, "undo"),
        ("escape", False, False, "clear_selection"),
        ("3", False, False, "rig_camera"),
        ("f", False, True, "frame_all"),  # shift ignored without ctrl
    ],
)
def test_find(key, ctrl, shift, name):
    assert find(key, ctrl, shift).name == name


def test_unbound_and_held_keys_are_not_presses():
    assert find("x") is None and find("q") is None and find("w") is None and find("b", ctrl=True) is None
    assert set(held_keys()) == set("wasdqe")
    assert combo("z", True, True) == "ctrl+shift+z"


def test_key_press_runs_the_bound_action(monkeypatch):
    calls = []
    monkeypatch.setitem(interaction.ACTIONS, "quit", lambda v: calls.append("quit"))
    assert interaction.key_press(object(), "q", True, False) and calls == ["quit"]
    assert not interaction.key_press(object(), "x", False, False)
