"""Error types. Every user-facing failure is one of these and prints as one line."""

from __future__ import annotations

from dataclasses import dataclass


class DrivingSceneError(Exception):
    """Base class: an error the command line reports as one line, without a traceback."""


class InputError(DrivingSceneError):
    """A file, argument or value given by the user is not what was expected."""


class OutputError(InputError):
    """A file could not be written where the user asked (read-only folder, full disk, no such folder)."""


@dataclass(frozen=True)
class Problem:
    """One finding of a validator: where, what was expected, what was found."""

    source: str  # file name (or "<memory>")
    key: str  # field / array key
    expected: str
    found: str

    def __str__(self) -> str:
        return f"{self.source}: {self.key}: expected {self.expected}, found {self.found}"


class SceneFormatError(InputError):
    """A scene or reconstruction file fails validation. Holds every problem found."""

    def __init__(self, problems: list[Problem]):
        self.problems = list(problems)
        first = str(self.problems[0]) if self.problems else "invalid file"
        more = f" (and {len(self.problems) - 1} more problem(s))" if len(self.problems) > 1 else ""
        super().__init__(first + more)
