"""The early stop of an unforced run (langfield/training/stopping.py) and its record in field.json."""

from __future__ import annotations

import pytest

from langfield import TrainConfig, load_scene, train
from langfield.training import setup as T
from langfield.training import stopping as S
from langfield.training.loop import LOSS_LOG_EVERY
from langfield.training.stopping import PlateauStop


def _stretches(values: dict[str, list[float]], first: int = 0, partial: str | None = None) -> list[dict]:
    """LossLog-like entries: stretch k of every term's k-th value (``partial``: a term that ran on half
    of each stretch's iterations)."""
    n = len(next(iter(values.values())))
    out = []
    for k in range(n):
        lo = first + k * LOSS_LOG_EVERY
        steps = {t: (LOSS_LOG_EVERY // 2 if t == partial else LOSS_LOG_EVERY) for t in values}
        terms = {t: v[k] for t, v in values.items()}
        out.append({"iterations": [lo, lo + LOSS_LOG_EVERY - 1], "terms": terms, "steps": steps,
                    "total": sum(terms.values())})  # fmt: skip
    return out


def test_a_falling_loss_runs_on_and_a_flat_one_stops_with_its_figures() -> None:
    stop = PlateauStop(0.01, first_step=0)
    falling = [1.0 * 0.97**k for k in range(12)]  # 3 % a stretch: always a real gain
    assert not stop.levelled(_stretches({"color": falling}))
    flat = [1.0, 0.9, 0.8, 0.7, 0.699, 0.6985, 0.6982, 0.698]
    assert stop.levelled(_stretches({"color": flat}))
    ev = stop.evidence["color"]
    assert ev["best_before"] == pytest.approx(0.7) and ev["best_recent"] == pytest.approx(0.698)
    assert 0 < ev["gain"] < 0.01


def test_too_few_stretches_the_coarse_start_and_a_running_term_hold_the_stop() -> None:
    flat = [0.5] * (S.PATIENCE + S.MIN_BEFORE)
    assert not PlateauStop(0.01, 0).levelled(_stretches({"color": flat[:-1]}))  # no baseline yet
    assert PlateauStop(0.01, 0).levelled(_stretches({"color": flat}))
    # The coarse start's stretches (lower loss at half size) are not compared with the full-size ones.
    coarse = _stretches({"color": [0.1] * 4})
    full = _stretches({"color": [0.5] * (S.PATIENCE + S.MIN_BEFORE - 1)}, first=4 * LOSS_LOG_EVERY)
    assert not PlateauStop(0.01, 4 * LOSS_LOG_EVERY).levelled(coarse + full)
    # The language term still falling keeps the run going although the colour term is flat.
    both = {"color": flat * 2, "language": [1.0 * 0.9**k for k in range(2 * len(flat))]}
    assert not PlateauStop(0.01, 0).levelled(_stretches(both))
    # A term that did not run throughout a stretch (it started within it) is not judged on it.
    assert PlateauStop(0.01, 0).levelled(_stretches({"color": flat, "language": flat}, partial="language"))
    with pytest.raises(ValueError, match="tolerance"):
        PlateauStop(0.0, 0)


def test_a_pruning_round_restarts_the_comparison() -> None:
    # A LOP round at stretch 6 raises the loss; the refit that follows is progress, not a plateau.
    values = [1.0, 0.8, 0.7, 0.65, 0.64, 0.635, 0.70, 0.66, 0.655, 0.655]
    entries = _stretches({"color": values})
    assert PlateauStop(0.01, 0).levelled(entries)  # compared across the round: "no gain"
    stop = PlateauStop(0.01, 0)
    stop.restart(6 * LOSS_LOG_EVERY)
    assert not stop.levelled(entries)  # four stretches since the round: no baseline yet
    stop.restart(2 * LOSS_LOG_EVERY)  # an earlier edit never moves the start back
    assert stop.first_step == 6 * LOSS_LOG_EVERY
    flat_after = _stretches({"color": values + [0.655] * 2})
    assert stop.levelled(flat_after)
    assert stop.evidence["color"]["best_before"] == pytest.approx(0.66)


def test_an_unforced_run_stops_early_and_says_why(room_factory, monkeypatch) -> None:
    scene = load_scene(room_factory(64, 48))
    monkeypatch.setattr(T, "ITERATIONS_PER_VIEW", 100)
    monkeypatch.setattr(T, "MIN_ITERATIONS", 1)
    monkeypatch.setattr(S, "PATIENCE", 1)
    monkeypatch.setattr(S, "MIN_BEFORE", 1)
    base = {"num_gaussians": 300, "densify": False, "language": False, "depth": False}
    # Any gain under 100 % counts as levelled: the stop comes at its first chance, the second stretch.
    field = train(scene, TrainConfig(stop_plateau=1.0, half_resolution_until=0.0, **base), progress=False)
    stopped = field.meta["stopped"]
    assert field.meta["iterations"] == 2 * LOSS_LOG_EVERY < 300
    assert stopped["reason"] == "plateau" and stopped["iteration"] == 100 and stopped["length"] == 300
    assert set(stopped["terms"]) == {"color"} and stopped["tolerance"] == 1.0
    assert sum(1 for _ in field.meta["loss_terms"]) == 2
    # --iterations forces the count; stop_plateau 0 runs the scene's length.
    forced = train(scene, TrainConfig(iterations=150, stop_plateau=1.0, **base), progress=False)
    assert forced.meta["iterations"] == 150 and forced.meta["stopped"]["reason"] == "forced"
    monkeypatch.setattr(T, "ITERATIONS_PER_VIEW", 40)
    whole = train(scene, TrainConfig(stop_plateau=0.0, half_resolution_until=0.0, **base), progress=False)
    assert whole.meta["iterations"] == 120 and whole.meta["stopped"]["reason"] == "length"
