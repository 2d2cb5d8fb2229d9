"""Quitting with unsaved edits: Ctrl+Q, File > Quit and the window's close button all ask first
(save / discard / cancel) when the document holds edits that are not saved, and quit at once
otherwise. Esc never quits. This module decides; ``panels/quit.py`` draws the question.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

ANSWERS = ("save", "discard", "cancel")


def has_unsaved_edits(doc) -> bool:
    """True when ``doc`` (a ``SceneDoc`` or None) holds edits not written by ``save_edited`` (a change
    of the selection alone is not saved, so it does not count)."""
    return doc is not None and bool(doc.edited)


def can_save(doc) -> bool:
    """recon.npz needs a rig: a PLY from another tool can only be exported."""
    return doc is not None and doc.num_views > 0


def default_save_path(doc) -> Path:
    """Where Save in the question writes: ``<source stem>_edited.npz`` beside the source (as the Save
    dialog proposes; ``save_edited`` picks a free name when it is taken)."""
    if doc.source is None:
        return Path.cwd() / "recon_edited.npz"
    return doc.source.parent / f"{doc.source.stem}_edited.npz"


@dataclass
class QuitGuard:
    """``asking``: the unsaved-edits question is shown; ``confirmed``: the window should close."""

    asking: bool = False
    confirmed: bool = False

    def request(self, doc) -> None:
        """Quit asked for (Ctrl+Q, File > Quit, the close button)."""
        if has_unsaved_edits(doc):
            self.asking = True
        else:
            self.confirmed = True

    def answer(self, choice: str, save: Callable[[], object] | None = None) -> None:
        """The user's answer; ``save`` writes the edits and returns None when that failed (then the
        window stays open, with the error in the status bar)."""
        if choice not in ANSWERS:
            raise ValueError(f"quit answer: expected one of {', '.join(ANSWERS)}, found {choice!r}")
        self.asking = False
        if choice == "discard":
            self.confirmed = True
        elif choice == "save":
            if save is None:
                raise ValueError("quit answer 'save' needs a save function")
            self.confirmed = save() is not None
