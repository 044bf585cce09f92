"""Tests of langfield.kernels' process settings."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

# A 48 MB block allocated, filled and freed four times; prints the page faults of the last time. The
# second time can still miss (about 1 run in 5): a small block placed behind the first one leaves its
# freed space a few bytes short of torch's aligned request, so the heap grows once more; from then on
# a freed block of the size is at hand, as in a training loop's steady state.
_PROBE = """
import resource, torch
from langfield.kernels import reuse_freed_memory
print(reuse_freed_memory())
for _ in range(4):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    block = torch.ones(6_000_000, dtype=torch.float64)
    del block
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _second_faults(setting: str | None) -> tuple[str, int]:
    env = {k: v for k, v in os.environ.items() if k != "LANGFIELD_MALLOC"}
    if setting is not None:
        env["LANGFIELD_MALLOC"] = setting
    out = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True, text=True, check=True)
    took, faults = out.stdout.split()
    return took, int(faults)


def test_reuse_freed_memory_spares_the_page_faults_of_a_block_freed_and_allocated_again() -> None:
    took, faults = _second_faults(None)
    if took != "True":
        pytest.skip("not glibc: reuse_freed_memory leaves malloc alone")
    # 48 MB is 11,719 pages of 4 KB: glibc's defaults map it afresh (one fault per page), the setting
    # hands back the freed block.
    assert faults < 1000
    took_system, faults_system = _second_faults("system")
    assert took_system == "False" and faults_system > 10_000


@pytest.mark.parametrize(
    ("given", "expected"),
    [
        ({}, "ACTIVE 3000"),  # the short spin
        ({"GOMP_SPINCOUNT": "50"}, "None 50"),  # the user's own spin
        ({"OMP_WAIT_POLICY": "PASSIVE"}, "PASSIVE None"),  # the user's own policy
    ],
)
def test_import_sets_a_short_openmp_spin_unless_the_user_chose(given: dict, expected: str) -> None:
    env = {k: v for k, v in os.environ.items() if k not in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY")}
    probe = "import os, langfield; print(os.environ.get('OMP_WAIT_POLICY'), os.environ.get('GOMP_SPINCOUNT'))"
    out = subprocess.run(
        [sys.executable, "-c", probe], env={**env, **given}, capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == expected
