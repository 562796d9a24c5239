"""Paired differences between two evaluations of the same queries, with a bootstrap confidence interval.

With a few hundred queries a difference of a few Recall@N points can be noise. Two evaluations of the
same query set (e.g. one checkpoint with and without a mask) are paired by query: the difference of
their hit rates is resampled over the queries (percentile bootstrap), so the interval says which gains
the query sample supports.
"""

from __future__ import annotations

from collections.abc import Sequence
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

    def record(self, level: float = LEVEL) -> dict[str, object]:
        """The fields a data file keeps of it (rounded to 0.01 points): ``gain``, ``ci_low``, ``ci_high``,
        ``excludes_0`` (yes / no) and the interval's ``level``."""
        return {
            "gain": round(self.gain, 2),
            "ci_low": round(self.low, 2),
            "ci_high": round(self.high, 2),
            "excludes_0": "yes" if self.significant else "no",
            "level": level,
        }

    def text(self) -> str:
        """``+3.5 [+0.5, +6.5]`` (a typographic minus)."""
        return f"{self.gain:+.1f} [{self.low:+.1f}, {self.high:+.1f}]".replace("-", "−")


def _check(*runs: np.ndarray) -> list[np.ndarray]:
    """Per-query hit rates as float arrays of one 1-D shape."""
    arrays = [np.asarray(r, dtype=np.float64) for r in runs]
    shapes = {a.shape for a in arrays}
    if len(shapes) != 1 or arrays[0].ndim != 1 or not len(arrays[0]):
        raise ValueError(f"paired hits must be 1-D arrays of the same length, got {[a.shape for a in arrays]}")
    return arrays


def _resampled_means(diffs: np.ndarray, resamples: int, seed: int) -> np.ndarray:
    """(resamples, k) means of the k rows of ``diffs`` (k, n), every row resampled over the same queries."""
    rng = np.random.default_rng(seed)
    n = diffs.shape[1]
    means = np.empty((resamples, len(diffs)))
    for start in range(0, resamples, 1000):  # chunks keep the index matrix small for large query sets
        idx = rng.integers(0, n, size=(min(1000, resamples - start), n))
        means[start : start + len(idx)] = diffs[:, idx].mean(axis=2).T
    return means


def _interval(values: np.ndarray, level: float = LEVEL) -> tuple[float, float]:
    tail = 100.0 * (1 - level) / 2
    low, high = np.percentile(values, [tail, 100.0 - tail])
    return float(low), float(high)


def paired_gain(hits: np.ndarray, reference: np.ndarray, resamples: int = RESAMPLES, seed: int = 0) -> PairedGain:
    """Gain of ``hits`` over ``reference`` (per-query booleans or 0/1, the same queries in the same order),
    in percentage points, with a ``LEVEL`` percentile-bootstrap interval over the queries."""
    a, b = _check(hits, reference)
    diff = 100.0 * (a - b)
    low, high = _interval(_resampled_means(diff[None], resamples, seed)[:, 0])
    return PairedGain(float(diff.mean()), low, high, len(diff))


def pooled_gain(
    comparisons: Sequence[tuple[np.ndarray, np.ndarray]],
    level: float = LEVEL,
    resamples: int = RESAMPLES,
    seed: int = 0,
) -> PairedGain:
    """The mean gain of several paired comparisons over the same queries (``(hits, reference)`` each; query i is
    the same query, or the same place, in all of them), in percentage points, with a ``level`` percentile-bootstrap
    interval that resamples the queries jointly across the comparisons, so that their correlation (one query set,
    one model in several) is kept. Hits may be rates in [0, 1] (a query's hits averaged over seeds or draws)."""
    if not comparisons:
        raise ValueError("a pooled gain needs at least one comparison")
    arrays = _check(*(a for pair in comparisons for a in pair))
    diffs = 100.0 * np.stack([a - b for a, b in zip(arrays[::2], arrays[1::2], strict=True)])
    low, high = _interval(_resampled_means(diffs, resamples, seed).mean(axis=1), level)
    return PairedGain(float(diffs.mean()), low, high, diffs.shape[1])


def seeds_and_queries_gain(
    sets: Sequence[np.ndarray], level: float = LEVEL, resamples: int = RESAMPLES, seed: int = 0
) -> PairedGain:
    """The mean gain over independent query sets (``sets``: one (seeds, queries) array per set, each row a training
    seed's per-query hits minus its reference's, 0/1 or rates), every set weighted alike, with a ``level``
    interval from a two-level bootstrap: in each set the training seeds are resampled and, jointly for all of
    them, the queries. It counts the spread between seeds (what another training draw would give) beside the
    query sample's, which a bootstrap over the queries alone leaves out."""
    if not sets:
        raise ValueError("a gain over sets needs at least one set")
    diffs = [100.0 * np.asarray(d, dtype=np.float64) for d in sets]
    if any(d.ndim != 2 or not d.size for d in diffs):
        raise ValueError(f"each set must be a (seeds, queries) array, got {[d.shape for d in diffs]}")
    rng = np.random.default_rng(seed)
    totals = np.zeros(resamples)
    for d in diffs:
        n_seeds, n = d.shape
        for start in range(0, resamples, 1000):
            k = min(1000, resamples - start)
            queries = np.stack([np.bincount(rng.integers(0, n, n), minlength=n) for _ in range(k)]) / n
            seeds = np.stack([np.bincount(rng.integers(0, n_seeds, n_seeds), minlength=n_seeds) for _ in range(k)])
            per_seed = queries @ d.T  # (k, seeds): each seed's mean over the resampled queries
            totals[start : start + k] += (per_seed * seeds).sum(axis=1) / n_seeds
    low, high = _interval(totals / len(diffs), level)
    return PairedGain(float(np.mean([d.mean() for d in diffs])), low, high, sum(d.shape[1] for d in diffs))


def corrected_level(claims: int, level: float = LEVEL) -> float:
    """The coverage each of ``claims`` intervals needs for all of them to hold together at ``level``
    (Bonferroni: the error rate ``1 - level`` split evenly)."""
    if claims < 1:
        raise ValueError(f"claims must be at least 1, got {claims}")
    return 1.0 - (1.0 - level) / claims


@dataclass(frozen=True)
class RecoveredShare:
    """The share of a damage a fix undoes, (fixed − damaged) / (clean − damaged), its bootstrap interval and
    the query count."""

    share: float
    low: float
    high: float
    queries: int

    def text(self) -> str:
        """``62 % [40, 85]`` (a typographic minus)."""
        return f"{100 * self.share:.0f} % [{100 * self.low:.0f}, {100 * self.high:.0f}]".replace("-", "−")


def recovered_share(
    fixed: np.ndarray, damaged: np.ndarray, clean: np.ndarray, resamples: int = RESAMPLES, seed: int = 0
) -> RecoveredShare | None:
    """How much of the damage (``clean`` − ``damaged`` hit rates) ``fixed`` undoes, as a fraction (1: all of it,
    0: none, below 0: it does more damage), with a ``LEVEL`` percentile-bootstrap interval: numerator and
    denominator are resampled over the same queries. None where the damage's own interval does not exclude 0
    (a share of no established damage means nothing)."""
    f, d, c = _check(fixed, damaged, clean)
    means = _resampled_means(np.stack([f - d, c - d]), resamples, seed)
    if _interval(means[:, 1])[0] <= 0:
        return None
    ratio = np.divide(means[:, 0], means[:, 1], out=np.full(len(means), np.inf), where=means[:, 1] != 0)
    low, high = _interval(ratio)
    return RecoveredShare(float((f - d).mean() / (c - d).mean()), low, high, len(f))
