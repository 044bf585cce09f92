"""The loop's record of the loss terms (langfield/training/loop.py: LossLog)."""

from __future__ import annotations

import pytest
import torch

from langfield.training.loop import LOSS_LOG_EVERY, SHOWN_TERMS, LossLog


def test_loss_log_means_per_stretch_count_each_term_and_close_the_last_stretch() -> None:
    log = LossLog()
    n = 2 * LOSS_LOG_EVERY + 7
    for step in range(n):
        terms = {"color": torch.tensor(float(step))}
        if step % 2 == 0:
            terms["virtual"] = torch.tensor(1.0)
        log.add(step, sum(terms.values()), terms)
    entries = log.entries()
    assert [e["iterations"] for e in entries] == [
        [0, LOSS_LOG_EVERY - 1], [LOSS_LOG_EVERY, 2 * LOSS_LOG_EVERY - 1], [2 * LOSS_LOG_EVERY, n - 1]
    ]  # fmt: skip
    first, last = entries[0], entries[-1]
    assert first["terms"]["color"] == pytest.approx((LOSS_LOG_EVERY - 1) / 2)
    # A term that ran on half the iterations counts 0 on the others, so the terms add up to the total.
    assert first["steps"] == {"color": LOSS_LOG_EVERY, "virtual": LOSS_LOG_EVERY // 2}
    assert first["terms"]["virtual"] == pytest.approx(0.5)
    assert first["total"] == pytest.approx(sum(first["terms"].values()))
    assert last["steps"]["color"] == 7
    assert log.entries() == entries  # closing twice adds nothing


def test_loss_log_postfix_shows_the_largest_terms_of_the_last_step() -> None:
    log = LossLog()
    terms = {
        name: torch.tensor(value) for name, value in zip("abcde", (0.1, -3.0, 0.5, 2.0, 0.0), strict=True)
    }
    total = sum(terms.values())
    log.add(0, total, terms)
    shown = log.postfix(total)
    assert list(shown)[0] == "loss" and len(shown) == 1 + SHOWN_TERMS
    assert set(shown) - {"loss"} == {"b", "d", "c"}  # by size, a negative term too
