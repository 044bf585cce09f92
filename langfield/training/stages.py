"""Where a training iteration's seconds go: wall time per stage, for ``langfield bench`` (issue 42).

The loop and the loss terms mark their stages with ``run.clock.stage(name)``; the clock of a plain
``langfield train`` is switched off and costs a branch per stage. The stages do not nest: each second
of an iteration is in one of them or, outside them all, in ``other`` (the loop's own bookkeeping).
PyTorch runs CPU operations synchronously, so a stage's wall time is its operations' time; the
backward pass of every stage is one stage of its own (``backward``).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["STAGES", "StageClock"]

# In the order of an iteration.
STAGES = (
    "strategy",  # carving before the render; densification, pruning, opacity decay, LOP after
    "hash grids",  # the colour and language grids read once for the step's renders
    "render",  # the training view (with the hard depth where L_D needs it)
    "colour loss",  # L1 + D-SSIM on the training view
    "virtual view",  # the virtual camera's render, its warp and its L1 + D-SSIM
    "other terms",  # L_D, the language term and the regularisers
    "backward",
    "optimizer",
)


class StageClock:
    """Seconds per stage over the iterations run with it (``enabled``); a no-op otherwise."""

    def __init__(self, enabled: bool = True) -> None:
        self.enabled = enabled
        self.seconds: dict[str, float] = dict.fromkeys(STAGES, 0.0)
        self.iteration_seconds = 0.0
        self.iterations = 0

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        if not self.enabled:
            yield
            return
        if name not in self.seconds:
            raise ValueError(f"unknown training stage {name!r}; stages: {', '.join(STAGES)}")
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] += time.perf_counter() - t0

    def add_iteration(self, seconds: float) -> None:
        """Counts one iteration that took ``seconds`` in all (its stages and the rest)."""
        if self.enabled:
            self.iteration_seconds += seconds
            self.iterations += 1

    def report(self) -> dict:
        """``{"iterations", "seconds", "stages": {name: {"seconds", "share"}}}``, ``other`` included."""
        stages = dict(self.seconds, other=max(self.iteration_seconds - sum(self.seconds.values()), 0.0))
        total = self.iteration_seconds
        return {
            "iterations": self.iterations,
            "seconds": total,
            "stages": {
                name: {"seconds": s, "share": s / total if total > 0 else None} for name, s in stages.items()
            },
        }
