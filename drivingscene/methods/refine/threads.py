"""How many threads each phase of the refinement runs on, chosen by timing (`ThreadChoice`), and
what a phase's next step should take (`typical_step`)."""

from __future__ import annotations

import statistics

import torch


class ThreadChoice:
    """The threads of one phase's steps (the adaptation's, the gradient steps'), chosen by timing
    where ``RefineConfig.threads`` is None: the phase's first step runs on torch's threads (a
    warm-up: caches, allocations), the second on one thread, the third on torch's again, and the
    faster of those two runs the rest. Refinement's tensors are small: on a quiet 2-core machine two
    threads made a step 1.6 times faster than one, but with one other busy process 2.8 times slower
    (docs/refinement.md, *Seconds per step*), and neither the load average (which counts this
    process too) nor the core count tells the two apart beforehand. With one thread to start with
    there is nothing to choose."""

    def __init__(self, many: int):
        self.many = max(1, int(many))
        self.trials: dict[int, float] = {}
        self.steps = 0
        self.chosen: int | None = None if self.many > 1 else 1

    def threads(self) -> int:
        """The threads of the next step."""
        if self.chosen is not None:
            return self.chosen
        return 1 if self.steps == 1 else self.many

    def record(self, threads: int, seconds: float) -> None:
        """A step's time on ``threads``; after the two trials the faster setting is kept (ties: one thread)."""
        if self.chosen is None and self.steps >= 1:
            self.trials[threads] = seconds
            if len(self.trials) == 2:
                self.chosen = min(sorted(self.trials), key=self.trials.get)
        self.steps += 1

    def begin_step(self) -> int:
        """Set torch's threads for the next step; returns them."""
        threads = self.threads()
        if torch.get_num_threads() != threads:
            torch.set_num_threads(threads)
        return threads


def typical_step(choice: ThreadChoice | None, times: list[float], threads_of: list[int]) -> float:
    """What the next step of a phase should take: the median of its step ``times`` (``threads_of``:
    each step's threads) that ran on the setting ``choice`` chose, or of all of them before a choice
    or where the threads are fixed (``choice`` None); 0 before any step."""
    chosen = [t for t, n in zip(times, threads_of) if choice is None or choice.chosen in (None, n)]
    return statistics.median(chosen or times) if times else 0.0
