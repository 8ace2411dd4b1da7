"""Intervals for success rates, clustered by object.

Trials of one object are not independent (an object that suits a method succeeds in most of its
trials), so the interval of a rate comes from the bootstrap over objects: draw the objects with
replacement, pool all their trials, take the rate; the 2.5 and 97.5 percentiles of 2,000 draws.
A difference between two methods is bootstrapped the same way on the objects both ran (paired: the
same draw of objects for both).
"""
from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

DRAWS = 2000
SEED = 0


@dataclass(frozen=True)
class Interval:
    value: float
    low: float
    high: float

    def __str__(self) -> str:
        return f"{self.value:.1%} [{self.low:.1%}, {self.high:.1%}]"

    def points(self) -> str:
        """As a difference in percentage points."""
        return f"{self.value * 100:+.1f} [{self.low * 100:+.1f}, {self.high * 100:+.1f}]"

    def as_dict(self) -> dict[str, float]:
        return {"value": self.value, "low": self.low, "high": self.high}


def _succeeded(record: dict[str, Any]) -> float:
    return float(bool(record["success"]))


def _per_object(records: Sequence[dict[str, Any]], cluster: str,
                value: Callable[[dict[str, Any]], float] = _succeeded) -> dict[str, tuple[float, int]]:
    """(sum of `value`, trials) per object: (successes, trials) by default."""
    counts: dict[str, list[float]] = defaultdict(lambda: [0.0, 0])
    for r in records:
        counts[r[cluster]][0] += value(r)
        counts[r[cluster]][1] += 1
    return {k: (v[0], int(v[1])) for k, v in counts.items()}


def success_interval(records: Sequence[dict[str, Any]], cluster: str = "object_id", draws: int = DRAWS,
                     seed: int = SEED) -> Interval:
    """The pooled success rate of `records` with its object-clustered 95% bootstrap interval."""
    return mean_interval(records, _succeeded, cluster, draws, seed)


def mean_interval(records: Sequence[dict[str, Any]], value: Callable[[dict[str, Any]], float],
                  cluster: str = "object_id", draws: int = DRAWS, seed: int = SEED) -> Interval:
    """The mean of `value` over `records` (e.g. corrections per trial) with its object-clustered 95% interval."""
    counts = _per_object(records, cluster, value)
    if not counts:
        return Interval(float("nan"), float("nan"), float("nan"))
    successes, trials = (np.array(v, dtype=np.float64) for v in zip(*counts.values(), strict=True))
    picks = np.random.default_rng(seed).integers(0, len(trials), size=(draws, len(trials)))
    rates = successes[picks].sum(axis=1) / trials[picks].sum(axis=1)
    return Interval(float(successes.sum() / trials.sum()), *(float(v) for v in np.percentile(rates, [2.5, 97.5])))


def difference_interval(a: Sequence[dict[str, Any]], b: Sequence[dict[str, Any]], cluster: str = "object_id",
                        draws: int = DRAWS, seed: int = SEED) -> Interval:
    """Success rate of `a` minus that of `b` on the objects both ran, with its paired clustered interval."""
    counts_a, counts_b = _per_object(a, cluster), _per_object(b, cluster)
    shared = sorted(set(counts_a) & set(counts_b))
    if not shared:
        return Interval(float("nan"), float("nan"), float("nan"))
    sa, ta = (np.array(v, dtype=np.float64) for v in zip(*(counts_a[k] for k in shared), strict=True))
    sb, tb = (np.array(v, dtype=np.float64) for v in zip(*(counts_b[k] for k in shared), strict=True))
    picks = np.random.default_rng(seed).integers(0, len(shared), size=(draws, len(shared)))
    diffs = sa[picks].sum(axis=1) / ta[picks].sum(axis=1) - sb[picks].sum(axis=1) / tb[picks].sum(axis=1)
    value = sa.sum() / ta.sum() - sb.sum() / tb.sum()
    return Interval(float(value), *(float(v) for v in np.percentile(diffs, [2.5, 97.5])))
