"""When training stops: the scene's length, or earlier once the fit has levelled off.

The run's length (:func:`langfield.training.setup.training_length`, 500 iterations per training view)
sets every schedule: the position learning rate's decay, the coarse start, the language start,
densification. Where the length was not forced (``--iterations``), :class:`PlateauStop` ends the run
earlier once the photometric fit of the training views stops improving. No held-out view is read.

The signal is the colour term's mean over each stretch of ``LOSS_LOG_EVERY`` iterations (the stretches
field.json's ``loss_terms`` records), and the language term's alike once it runs. One iteration's term
is noisy (dropout, a random background, a random virtual camera); a 50-iteration mean is not. Only
stretches at full resolution count: the coarse start's half-size renders fit more easily, so their
loss is lower and no full-size stretch would beat it. Likewise only the stretches after the last LOP
round count (:meth:`PlateauStop.restart`): a round removes Gaussians, the loss rises, and stretches
before it would make the refit look like no progress. The run stops at the end of a stretch when, for
each watched term, the best of the last ``PATIENCE`` stretches is within ``stop_plateau`` (a fraction)
of the best before them, and at least ``MIN_BEFORE`` full-size stretches came before those.

On LLFF fern (defaults, 1500 iterations) the colour term's means fall 3.5 % between the stretches
800-999 and those before, 1.2 % at 1000-1199, 0.45 % at 1100-1299 (one run; see docs/decisions.md,
``stop_plateau``, for where runs stop at 1 % and 0.5 %).
"""

from __future__ import annotations

from typing import Any

PATIENCE = 4  # stretches (of LOSS_LOG_EVERY iterations) that must bring no real improvement
MIN_BEFORE = 2  # full-size stretches before those, so that the comparison has a baseline
WATCHED = ("color", "language")  # the fitting terms; a term not (yet) running is not watched


class PlateauStop:
    """Says when a run's fitting terms have levelled off (see the module docstring).

    Args:
        tolerance: the fraction the best recent stretch must improve on the best before it by (> 0).
        first_step: the first iteration whose stretch counts (the end of the coarse start).
    """

    def __init__(self, tolerance: float, first_step: int) -> None:
        if not tolerance > 0:
            raise ValueError(f"PlateauStop: tolerance must be > 0, got {tolerance!r}")
        self.tolerance = float(tolerance)
        self.first_step = int(first_step)
        self.evidence: dict[str, Any] | None = None

    def restart(self, iteration: int) -> None:
        """Counts only the stretches from ``iteration`` on (the Gaussian set was edited there)."""
        self.first_step = max(self.first_step, int(iteration))

    def levelled(self, entries: list[dict[str, Any]]) -> bool:
        """Whether the stretches so far (LossLog entries, oldest first) show every watched term levelled
        off; the figures behind a True are kept in :attr:`evidence`."""
        full = [e for e in entries if e["iterations"][0] >= self.first_step]
        found = {}
        for term in WATCHED:
            # A term counts from its first stretch that ran on every iteration.
            values = [e["terms"][term] for e in full if _ran_throughout(e, term)]
            if not values:
                continue
            if len(values) < PATIENCE + MIN_BEFORE:
                return False
            before, recent = min(values[:-PATIENCE]), min(values[-PATIENCE:])
            gain = (before - recent) / before if before > 0 else 0.0
            if gain >= self.tolerance:
                return False
            found[term] = {"best_before": before, "best_recent": recent, "gain": gain}
        if not found:
            return False
        self.evidence = found
        return True


def _ran_throughout(entry: dict[str, Any], term: str) -> bool:
    steps = entry["steps"].get(term, 0)
    return term in entry["terms"] and steps == entry["iterations"][1] - entry["iterations"][0] + 1
