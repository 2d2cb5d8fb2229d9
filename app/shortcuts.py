"""Every keyboard shortcut of the window, in one table: the key handler (``interaction.key_press``)
looks keys up here and Help > Controls lists this table, so the two cannot drift apart.

A key is named as the window reports it: a lower-case name ('z', 'escape', 'left', '1'), with
'ctrl+' and then 'shift+' in front when those are held. ``held`` keys (fly) are read every frame
instead of handled on a press.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Shortcut:
    name: str  # the action the key handler runs (``interaction.ACTIONS``)
    keys: tuple[str, ...]  # key names with 'ctrl+' / 'shift+' prefixes
    label: str  # the keys as Help writes them
    text: str  # what they do
    held: bool = False  # read every frame while down (not a press)


SHORTCUTS = (
    Shortcut("open", ("ctrl+o",), "Ctrl+O", "open a scene, reconstruction or PLY"),
    Shortcut("save", ("ctrl+s",), "Ctrl+S", "save the edited reconstruction"),
    Shortcut("quit", ("ctrl+q",), "Ctrl+Q", "quit (asks first when edits are unsaved)"),
    Shortcut("undo", ("ctrl+z",), "Ctrl+Z", "undo"),
    Shortcut("redo", ("ctrl+shift+z", "ctrl+y"), "Ctrl+Shift+Z, Ctrl+Y", "redo"),
    Shortcut("select_all", ("ctrl+a",), "Ctrl+A", "select all"),
    Shortcut("clear_selection", ("escape",), "Esc", "clear the selection, back to navigate (in a menu or dialog: close it)"),
    Shortcut("invert_selection", ("i",), "I", "invert the selection"),
    Shortcut("hide_selected", ("h",), "H", "hide the selection"),
    Shortcut("delete_selected", ("delete",), "Delete", "delete the selection"),
    Shortcut("fly", ("w", "a", "s", "d", "q", "e"), "W A S D, Q E", "fly (shift: faster)", held=True),
    Shortcut("frame_all", ("f",), "F", "frame all"),
    Shortcut("reset_camera", ("r",), "R", "reset the camera"),
    Shortcut("rig_camera", tuple("123456789"), "1-9", "look through rig camera 1-9"),
    Shortcut("free_camera", ("0",), "0", "free camera"),
    Shortcut("follow_ego", ("g",), "G", "follow the ego vehicle"),
    Shortcut("play", ("space",), "Space", "play / pause"),
    Shortcut("step_back", ("left", "comma"), "Left, Comma", "step time back"),
    Shortcut("step_forward", ("right", "period"), "Right, Period", "step time forward"),
    Shortcut("first_keyframe", ("home",), "Home", "go to keyframe 0 (t = 0)"),
    Shortcut("last_keyframe", ("end",), "End", "go to keyframe 1 (t = 1)"),
)

MOUSE = (
    ("left drag", "orbit (fly mode: look around)"),
    ("right / middle / shift+left drag", "pan"),
    ("wheel", "zoom"),
    ("shift / ctrl + select", "add / subtract"),
)

_BY_KEY = {key: s for s in SHORTCUTS if not s.held for key in s.keys}


def combo(key: str, ctrl: bool = False, shift: bool = False) -> str:
    """``'z', ctrl, shift`` -> ``'ctrl+shift+z'``."""
    return ("ctrl+" if ctrl else "") + ("shift+" if shift else "") + key


def find(key: str, ctrl: bool = False, shift: bool = False) -> Shortcut | None:
    """The shortcut of a key press; shift is ignored where no shift variant exists (without ctrl)."""
    found = _BY_KEY.get(combo(key, ctrl, shift))
    if found is None and shift and not ctrl:
        found = _BY_KEY.get(key)
    return found


def held_keys() -> tuple[str, ...]:
    """The keys read every frame (fly)."""
    return tuple(key for s in SHORTCUTS if s.held for key in s.keys)
