"""The open scene: Gaussians (editable), hidden and selected flags, and every edit with undo.

``SceneDoc.edit`` is the one place edits go through: it applies the edit and records it in the
bounded ``History``. Version counters tell the renderer what to re-upload (``geometry`` after a
delete, ``flows`` after a flow edit, ``flags`` after hide/select). ``ViewState`` is the rest of
what the user controls (time, playback, display mode), kept apart from the document.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from drivingscene_view.edits import CompoundEdit, DeleteEdit, Edit, FlowEdit, HideEdit, History, ReplaceEdit, SelectEdit
from drivingscene_view.splats import SplatArrays

from drivingscene.gaussians.core import Gaussians
from drivingscene.gaussians.recon import Reconstruction
from drivingscene.gaussians.timing import DEFAULT_BLEND

SELECT_MODES = ("replace", "add", "subtract")


@dataclass
class ViewState:
    """Time, playback and display settings (not part of the document, not undoable)."""

    t: float = 0.0  # normalised time in [0, 1]
    playing: bool = False
    loop: bool = True
    speed: float = 0.25  # playback speed relative to real time
    blend: str = DEFAULT_BLEND
    mode: str = "rgb"
    show_frusta: bool = True
    show_path: bool = True
    show_grid: bool = True
    show_selection: bool = True
    depth_range: tuple[float, float] = (2.0, 80.0)  # metres, near/far of the depth colour map
    flow_max: float = 2.0  # metres at the top of the flow-magnitude colour map


class SceneDoc:
    """A reconstruction opened in the viewer, with its edits."""

    def __init__(
        self, recon: Reconstruction, source: Path | None = None, info: dict | None = None, budget_bytes: int = 256 << 20
    ):
        self.recon = recon
        self.source = source
        self.info = dict(info or {})  # kind, method, seconds, ...
        self.splats = SplatArrays.from_gaussians(recon.gaussians)
        n = len(self.splats)
        self.hidden = np.zeros(n, bool) if recon.hidden is None else recon.hidden.cpu().numpy().astype(bool)
        self.selected = np.zeros(n, bool)
        self.history = History(budget_bytes)
        self.versions = {"geometry": 0, "flows": 0, "flags": 0}
        self.edited = False
        self.origin = np.round(self.splats.means.mean(axis=0).astype(np.float64)) if n else np.zeros(3)

    # --- low-level setters (used by edits only) ----------------------------------------------
    def set_selected(self, selected: np.ndarray) -> None:
        self.selected = selected
        self.versions["flags"] += 1

    def set_hidden(self, hidden: np.ndarray) -> None:
        self.hidden = hidden
        self.versions["flags"] += 1

    def set_flows(self, flows: np.ndarray) -> None:
        self.splats = self.splats.with_flows(flows)
        self.versions["flows"] += 1

    def set_splats(self, splats: SplatArrays, hidden: np.ndarray, selected: np.ndarray) -> None:
        self.splats, self.hidden, self.selected = splats, hidden, selected
        self.versions["geometry"] += 1

    # --- the one entry point for changes -----------------------------------------------------
    def edit(self, edit: Edit) -> None:
        edit.apply(self)
        self.history.push(edit)
        self.edited |= changes_content(edit)

    def undo(self) -> str | None:
        edit = self.history.pop_undo()
        if edit is not None:
            edit.revert(self)
            self.edited |= changes_content(edit)
        return None if edit is None else edit.label

    def redo(self) -> str | None:
        edit = self.history.pop_redo()
        if edit is not None:
            edit.apply(self)
            self.edited |= changes_content(edit)
        return None if edit is None else edit.label

    # --- user operations ---------------------------------------------------------------------
    def select(self, mask: np.ndarray, mode: str = "replace", label: str = "select") -> None:
        """Combine ``mask`` with the selection; hidden Gaussians are never selected."""
        if mode == "add":
            new = self.selected | mask
        elif mode == "subtract":
            new = self.selected & ~mask
        else:
            new = mask.copy()
        new &= ~self.hidden
        if not np.array_equal(new, self.selected):
            self.edit(SelectEdit.create(self.selected, new, label))

    def select_dynamic(self, mode: str = "replace") -> None:
        self.select(self.splats.dynamic, mode, "select dynamic")

    def select_opacity_below(self, threshold: float, mode: str = "replace") -> None:
        self.select(self.splats.opacities < threshold, mode, f"select opacity < {threshold:g}")

    def invert_selection(self) -> None:
        self.select(~self.selected, "replace", "invert selection")

    def clear_selection(self) -> None:
        self.select(np.zeros_like(self.selected), "replace", "clear selection")

    def hide_selected(self) -> None:
        index = np.flatnonzero(self.selected & ~self.hidden)
        if len(index):
            deselect = SelectEdit.create(self.selected, np.zeros_like(self.selected), "deselect")
            self.edit(CompoundEdit((deselect, HideEdit(index, True)), f"hide {len(index)}"))

    def unhide_all(self) -> None:
        index = np.flatnonzero(self.hidden)
        if len(index):
            self.edit(HideEdit(index, False, "unhide all"))

    def delete_selected(self) -> None:
        if self.selected.any():
            self.edit(DeleteEdit.create(self, self.selected, label=f"delete {int(self.selected.sum())}"))

    def make_static_selected(self) -> None:
        index = np.flatnonzero(self.selected & self.splats.dynamic)
        if len(index):
            self.edit(FlowEdit.create(self, index, np.zeros((len(index), 3), np.float32), "make static"))

    def scale_flow_selected(self, factor: float) -> None:
        index = np.flatnonzero(self.selected & self.splats.dynamic)
        if len(index):
            self.edit(FlowEdit.create(self, index, self.splats.flows[index] * np.float32(factor), f"scale flow x{factor:g}"))

    def replace_reconstruction(self, refined: Reconstruction, label: str = "refine") -> None:
        """Take a refinement of ``to_reconstruction()`` (the same Gaussians, new values and maps) as
        one undoable edit; the Gaussians keep their identities, hidden and selected flags."""
        if len(refined.gaussians) != len(self.splats):
            raise ValueError(f"{label}: {len(refined.gaussians)} Gaussians came back for {len(self.splats)}")
        after = replace(SplatArrays.from_gaussians(refined.gaussians), uid=self.splats.uid)
        # The document keeps the rig and maps in ``recon``; its Gaussians live in ``splats``.
        lean = lambda r: replace(r, gaussians=Gaussians.empty(r.gaussians.sh_degree), hidden=None)  # noqa: E731
        self.edit(ReplaceEdit(self.splats, after, lean(self.recon), lean(refined), label))

    # --- views of the document ---------------------------------------------------------------
    @property
    def num_views(self) -> int:
        return self.recon.num_views

    @property
    def duration(self) -> float:
        return float(self.recon.timestamps[1] - self.recon.timestamps[0])

    def visible_gaussians(self):
        """Torch Gaussians that exports write: not deleted, not hidden."""
        return self.splats.to_gaussians(~self.hidden)

    def to_reconstruction(self) -> Reconstruction:
        """The edited reconstruction (deleted Gaussians gone, hidden ones flagged) for ``save_reconstruction``."""
        hidden = torch.from_numpy(self.hidden.copy()) if self.hidden.any() else None
        return replace(self.recon, gaussians=self.splats.to_gaussians(), hidden=hidden, meta={**self.recon.meta, "edited": True})

    def stats(self) -> dict[str, int]:
        """Counts (total, dynamic, hidden, selected), cached until the next change."""
        key = tuple(self.versions.values())
        if getattr(self, "_stats_key", None) != key:
            self._stats = {
                "total": len(self.splats),
                "dynamic": int(self.splats.dynamic.sum()),
                "hidden": int(self.hidden.sum()),
                "selected": int(self.selected.sum()),
            }
            self._stats_key = key
        return self._stats


def changes_content(edit: Edit) -> bool:
    """False for an edit of the selection alone: recon.npz does not store the selection, so it leaves
    nothing unsaved (the quit question and the "unsaved edits" note)."""
    if isinstance(edit, SelectEdit):
        return False
    if isinstance(edit, CompoundEdit):
        return any(changes_content(p) for p in edit.parts)
    return True


@dataclass
class Status:
    """The one-line message bar: the latest info or error."""

    text: str = ""
    error: bool = False
    actions: list = field(default_factory=list)  # (label, callable) offered beside an error
