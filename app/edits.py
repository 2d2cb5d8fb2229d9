"""Undoable edits of a ``SceneDoc`` and the bounded undo history.

Every edit stores only what it changed (packed selection bits, changed indices, removed rows, old
flows), reports its size in bytes, and can ``apply`` and ``revert`` itself. ``History`` keeps the
newest edits within a byte budget: the oldest are dropped first, and an edit larger than the whole
budget empties the history (it is applied but cannot be undone).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np
from drivingscene_view.splats import SplatArrays, insert_mask, insert_rows

if TYPE_CHECKING:
    from drivingscene_view.state import SceneDoc


class Edit(Protocol):
    label: str

    @property
    def nbytes(self) -> int: ...

    def apply(self, doc: SceneDoc) -> None: ...

    def revert(self, doc: SceneDoc) -> None: ...


@dataclass(frozen=True, eq=False)
class SelectEdit:
    """Replace the selection (stored as packed bits before and after)."""

    before: np.ndarray  # packed bits
    after: np.ndarray
    count: int
    label: str = "select"

    @classmethod
    def create(cls, old: np.ndarray, new: np.ndarray, label: str = "select") -> SelectEdit:
        return cls(np.packbits(old), np.packbits(new), len(new), label)

    @property
    def nbytes(self) -> int:
        return self.before.nbytes + self.after.nbytes

    def apply(self, doc: SceneDoc) -> None:
        doc.set_selected(np.unpackbits(self.after, count=self.count).astype(bool))

    def revert(self, doc: SceneDoc) -> None:
        doc.set_selected(np.unpackbits(self.before, count=self.count).astype(bool))


@dataclass(frozen=True, eq=False)
class HideEdit:
    """Set ``hidden[index] = value`` (only indices that change are stored)."""

    index: np.ndarray  # int64
    value: bool
    label: str = "hide"

    @property
    def nbytes(self) -> int:
        return self.index.nbytes

    def _set(self, doc: SceneDoc, value: bool) -> None:
        hidden = doc.hidden.copy()
        hidden[self.index] = value
        doc.set_hidden(hidden)

    def apply(self, doc: SceneDoc) -> None:
        self._set(doc, self.value)

    def revert(self, doc: SceneDoc) -> None:
        self._set(doc, not self.value)


@dataclass(frozen=True, eq=False)
class DeleteEdit:
    """Remove rows ``index`` (sorted); keeps them (and their flags) to put them back."""

    index: np.ndarray  # int64, sorted
    rows: SplatArrays
    hidden: np.ndarray
    selected: np.ndarray
    label: str = "delete"

    @classmethod
    def create(cls, doc: SceneDoc, mask: np.ndarray, label: str = "delete") -> DeleteEdit:
        index = np.flatnonzero(mask)
        return cls(index, doc.splats.take(index), doc.hidden[index], doc.selected[index], label)

    @property
    def nbytes(self) -> int:
        return self.index.nbytes + self.rows.nbytes() + self.hidden.nbytes + self.selected.nbytes

    def apply(self, doc: SceneDoc) -> None:
        keep = np.ones(len(doc.splats), bool)
        keep[self.index] = False
        doc.set_splats(doc.splats.take(keep), doc.hidden[keep], doc.selected[keep])

    def revert(self, doc: SceneDoc) -> None:
        doc.set_splats(
            insert_rows(doc.splats, self.index, self.rows),
            insert_mask(doc.hidden, self.index, self.hidden),
            insert_mask(doc.selected, self.index, self.selected),
        )


@dataclass(frozen=True, eq=False)
class FlowEdit:
    """Set the flows of rows ``index`` (make static, scale flow)."""

    index: np.ndarray  # int64
    before: np.ndarray  # [k, 3]
    after: np.ndarray  # [k, 3]
    label: str = "flow"

    @classmethod
    def create(cls, doc: SceneDoc, index: np.ndarray, new_flows: np.ndarray, label: str) -> FlowEdit:
        return cls(index, doc.splats.flows[index].copy(), np.asarray(new_flows, np.float32), label)

    @property
    def nbytes(self) -> int:
        return self.index.nbytes + self.before.nbytes + self.after.nbytes

    def _set(self, doc: SceneDoc, values: np.ndarray) -> None:
        flows = doc.splats.flows.copy()
        flows[self.index] = values
        doc.set_flows(flows)

    def apply(self, doc: SceneDoc) -> None:
        self._set(doc, self.after)

    def revert(self, doc: SceneDoc) -> None:
        self._set(doc, self.before)


@dataclass(frozen=True, eq=False)
class ReplaceEdit:
    """Replace every Gaussian's values and the reconstruction's maps by a refined version of the same
    Gaussians (same count and order: flags and identities stay); undo puts the old ones back."""

    before: SplatArrays
    after: SplatArrays
    recon_before: object  # Reconstruction
    recon_after: object
    label: str = "refine"

    @property
    def nbytes(self) -> int:
        maps = sum(
            getattr(r, k).nbytes
            for r in (self.recon_before, self.recon_after)
            for k in ("depth", "rigid_flow", "residual_flow")
            if getattr(r, k) is not None
        )
        return self.before.nbytes() + self.after.nbytes() + maps

    def apply(self, doc: SceneDoc) -> None:
        doc.recon = self.recon_after
        doc.set_splats(self.after, doc.hidden, doc.selected)

    def revert(self, doc: SceneDoc) -> None:
        doc.recon = self.recon_before
        doc.set_splats(self.before, doc.hidden, doc.selected)


@dataclass(frozen=True, eq=False)
class CompoundEdit:
    """Several edits undone and redone as one step."""

    parts: tuple
    label: str

    @property
    def nbytes(self) -> int:
        return sum(p.nbytes for p in self.parts)

    def apply(self, doc: SceneDoc) -> None:
        for p in self.parts:
            p.apply(doc)

    def revert(self, doc: SceneDoc) -> None:
        for p in reversed(self.parts):
            p.revert(doc)


class History:
    """Undo/redo stacks holding at most ``budget_bytes`` of edit data."""

    def __init__(self, budget_bytes: int = 256 << 20):
        self.budget_bytes = budget_bytes
        self.undo_stack: list[Edit] = []
        self.redo_stack: list[Edit] = []
        self.dropped = 0  # edits forgotten to stay within the budget

    @property
    def nbytes(self) -> int:
        return sum(e.nbytes for e in self.undo_stack) + sum(e.nbytes for e in self.redo_stack)

    def push(self, edit: Edit) -> None:
        self.redo_stack.clear()
        self.undo_stack.append(edit)
        while self.undo_stack and self.nbytes > self.budget_bytes:
            self.undo_stack.pop(0)
            self.dropped += 1

    def clear(self) -> None:
        self.undo_stack.clear()
        self.redo_stack.clear()

    def pop_undo(self) -> Edit | None:
        if not self.undo_stack:
            return None
        edit = self.undo_stack.pop()
        self.redo_stack.append(edit)
        return edit

    def pop_redo(self) -> Edit | None:
        if not self.redo_stack:
            return None
        edit = self.redo_stack.pop()
        self.undo_stack.append(edit)
        return edit
