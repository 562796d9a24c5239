"""Paired differences between two evaluations of the same queries, with a bootstrap confidence interval.

With a few hundred queries a difference of a few Recall@N points can be noise. Two evaluations of the
same query set (e.g. one checkpoint with and without a mask) are paired by query: the difference of
their hit rates is resampled over the queries (percentile bootstrap), so the interval says which gains
the query sample supports.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Bootstrap resamples and the interval's coverage.
RESAMPLES = 10_000
LEVEL = 0.95


@dataclass(frozen=True)
class PairedGain:
    """Mean difference of hit rates in percentage points, its bootstrap interval, and the query count."""

    gain: float
    low: float
    high: float
    queries: int

    @property
    def significant(self) -> bool:
        """Whether the interval excludes 0."""
        return self.low > 0 or self.high < 0

    def text(self) -> str:
        """``+3.5 [+0.5, +6.5]`` (a typographic minus)."""
        return f"{self.gain:+.1f} [{self.low:+.1f}, {self.high:+.1f}]".replace("-", "−")


def paired_gain(hits: np.ndarray, reference: np.ndarray, resamples: int = RESAMPLES, seed: int = 0) -> PairedGain:
    """Gain of ``hits`` over ``reference`` (per-query booleans or 0/1, the same queries in the same order),
    in percentage points, with a ``LEVEL`` percentile-bootstrap interval over the queries."""
    a, b = np.asarray(hits, dtype=np.float64), np.asarray(reference, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 1 or not len(a):
        raise ValueError(f"paired hits must be two 1-D arrays of the same length, got {a.shape} and {b.shape}")
    diff = 100.0 * (a - b)
    rng = np.random.default_rng(seed)
    means = np.empty(resamples)
    for start in range(0, resamples, 1000):  # chunks keep the index matrix small for large query sets
        idx = rng.integers(0, len(diff), size=(min(1000, resamples - start), len(diff)))
        means[start : start + len(idx)] = diff[idx].mean(axis=1)
    tail = 100.0 * (1 - LEVEL) / 2
    low, high = np.percentile(means, [tail, 100.0 - tail])
    return PairedGain(float(diff.mean()), float(low), float(high), len(diff))
