"""bench/prescreen_speed.py: how two prescreen decisions, and the critic's order, are compared (no physics)."""
from __future__ import annotations

from types import ModuleType

import numpy as np
import pytest

from conftest import load_bench


@pytest.fixture(scope="module")
def bench() -> ModuleType:
    return load_bench("prescreen_speed")


def test_the_planned_order_is_the_passing_poses_closest_first(bench: ModuleType) -> None:
    success = np.array([True, False, True, True])
    error = np.array([0.02, 0.0, 0.01, 0.03])
    assert bench.planned_order(success, error).tolist() == [2, 0, 3]


def test_the_critics_order_counts_its_first_poses_against_the_prescreens(bench: ModuleType) -> None:
    # the prescreen plans pose 2 first; the critic would have planned 0 and 1, of which 1 failed
    success = np.array([True, False, True, True])
    error = np.array([0.02, 0.0, 0.01, 0.03])
    row = bench.critic_compare((success, error), top=2)
    assert row["first_same"] is False
    assert row["top_overlap"] == pytest.approx(0.5)  # {0, 1} against {2, 0}
    assert (row["agree"], row["pushes"], row["passed"]) == (1, 2, 1)  # one of the critic's first two passed


def test_the_critics_order_is_the_prescreens_when_it_passes_in_order(bench: ModuleType) -> None:
    success = np.ones(6, dtype=bool)
    row = bench.critic_compare((success, np.linspace(0.0, 0.05, 6)), top=6)
    assert row["first_same"] is True and row["top_overlap"] == 1.0 and row["agree"] == 6


def test_a_replay_that_changes_nothing_agrees_everywhere(bench: ModuleType) -> None:
    decision = (np.array([True, False, True]), np.array([0.01, 0.2, 0.02]))
    row = bench.compare(decision, decision, top=6)
    assert row == {"first_same": True, "top_overlap": 1.0, "agree": 3, "pushes": 3, "passed_reference": 2, "passed": 2}
