"""Paired bootstrap gains: the mean difference of hit rates and an interval that covers what it should."""

from __future__ import annotations

import numpy as np
import pytest

from semvpr.reporting.paired import corrected_level, paired_gain, pooled_gain, recovered_share


def test_the_gain_is_the_difference_of_hit_rates_in_points() -> None:
    ref = np.array([1, 0, 0, 1, 0, 1, 0, 0, 1, 0] * 20, bool)
    new = ref.copy()
    new[[1, 2, 4]] = True  # three more queries found, out of 200
    gain = paired_gain(new, ref)
    assert gain.gain == pytest.approx(1.5) and gain.queries == 200
    assert gain.low <= gain.gain <= gain.high and gain.low >= 0.0  # no query got worse: never below 0


def test_identical_runs_give_a_zero_width_interval_and_no_significance() -> None:
    hits = np.random.default_rng(0).random(150) < 0.6
    gain = paired_gain(hits, hits)
    assert (gain.gain, gain.low, gain.high, gain.significant) == (0.0, 0.0, 0.0, False)


def test_the_interval_matches_the_normal_approximation_on_a_large_sample() -> None:
    """For n paired differences d_i in {-1, 0, 1} the 95 % interval of the mean is about mean ± 1.96 s/√n."""
    rng = np.random.default_rng(1)
    ref = rng.random(2000) < 0.5
    new = np.where(rng.random(2000) < 0.1, ~ref, ref) | (rng.random(2000) < 0.05)
    gain = paired_gain(new, ref, resamples=4000)
    d = 100.0 * (new.astype(float) - ref.astype(float))
    half = 1.96 * d.std(ddof=1) / np.sqrt(len(d))
    assert gain.low == pytest.approx(d.mean() - half, abs=0.35) and gain.high == pytest.approx(
        d.mean() + half, abs=0.35
    )


def test_a_small_gain_on_few_queries_is_not_significant_and_a_large_one_is() -> None:
    rng = np.random.default_rng(2)
    ref = rng.random(200) < 0.5
    small = ref.copy()
    small[np.flatnonzero(~ref)[:3]] = True
    small[np.flatnonzero(ref)[:1]] = False  # +2 points net on 200 queries
    assert not paired_gain(small, ref).significant
    large = ref | (rng.random(200) < 0.3)
    assert paired_gain(large, ref).significant and paired_gain(ref, large).high < 0


def test_the_pairing_must_be_on_the_same_queries() -> None:
    with pytest.raises(ValueError, match="same length"):
        paired_gain(np.ones(5), np.ones(6))


def test_the_recovered_share_is_the_part_of_the_damage_undone() -> None:
    """200 queries: 40 found clean are lost under damage; a fix that finds 10 of them again undoes a quarter,
    one that finds all 40 again undoes all of it in every resample, and no damage has no share."""
    clean = np.zeros(200, bool)
    clean[:100] = True
    damaged = clean.copy()
    damaged[:40] = False
    quarter = damaged.copy()
    quarter[:10] = True
    share = recovered_share(quarter, damaged, clean)
    assert share is not None and share.share == pytest.approx(0.25) and share.queries == 200
    assert 0.0 < share.low < 0.25 < share.high < 0.5
    full = recovered_share(clean, damaged, clean)
    assert full is not None and (full.share, full.low, full.high) == (1.0, 1.0, 1.0)
    worse = damaged.copy()
    worse[40:50] = False  # the fix loses 10 more
    assert recovered_share(worse, damaged, clean).high < 0
    assert recovered_share(quarter, clean, clean) is None


def test_a_pooled_gain_resamples_the_queries_jointly_across_its_comparisons() -> None:
    """The mean of several comparisons' gains, its interval the normal one of the per-query mean difference (an
    independent derivation); a comparison repeated adds no information (resampled jointly, not as new queries)."""
    rng = np.random.default_rng(3)
    n = 4000
    reference = rng.random((3, n)) < 0.5
    hits = reference ^ (rng.random((3, n)) < np.array([[0.10], [0.20], [0.30]]))
    pooled = pooled_gain(list(zip(hits, reference)))
    gains = [paired_gain(h, r).gain for h, r in zip(hits, reference)]
    assert pooled.gain == pytest.approx(np.mean(gains)) and pooled.queries == n
    per_query = 100.0 * (hits.astype(float) - reference).mean(axis=0)
    half = 1.96 * per_query.std(ddof=1) / np.sqrt(n)
    assert pooled.low == pytest.approx(pooled.gain - half, abs=0.1 * half)
    assert pooled.high == pytest.approx(pooled.gain + half, abs=0.1 * half)
    one = paired_gain(hits[0], reference[0])
    twice = pooled_gain([(hits[0], reference[0])] * 2)
    assert (twice.gain, twice.low, twice.high) == pytest.approx((one.gain, one.low, one.high))
    # Rates averaged over seeds are hits too; a corrected level widens the interval.
    rates = pooled_gain([(hits.mean(axis=0), reference.mean(axis=0))])
    assert rates.gain == pytest.approx(pooled.gain)
    wide = pooled_gain(list(zip(hits, reference)), level=corrected_level(5))
    assert wide.low < pooled.low and wide.high > pooled.high
    assert corrected_level(5) == pytest.approx(0.99) and corrected_level(1) == 0.95
    with pytest.raises(ValueError, match="same length"):
        pooled_gain([(hits[0], reference[0]), (hits[1][:10], reference[1][:10])])


def test_a_gain_over_seeds_and_sets_counts_the_seeds_spread() -> None:
    """Seeds that differ by whole offsets widen the interval (another training draw would move the gain); the
    point estimate is the mean over sets of the mean over seeds and queries; one seed of one set is a query
    bootstrap as paired_gain's."""
    from semvpr.reporting.paired import paired_gain, seeds_and_queries_gain

    rng = np.random.default_rng(3)
    n = 600
    noise = (rng.random((8, n)) < 0.5).astype(float) - (rng.random((8, n)) < 0.5)
    offsets = np.linspace(-0.2, 0.2, 8)[:, None]  # seed means from -20 to +20 points
    spread = np.clip(noise * 0.1 + offsets, -1, 1)
    tight = np.clip(noise * 0.1 + offsets.mean(), -1, 1)
    wide = seeds_and_queries_gain([spread, spread[::-1]])
    narrow = seeds_and_queries_gain([tight, tight])
    assert np.isclose(wide.gain, 100 * spread.mean()) and np.isclose(narrow.gain, 100 * tight.mean())
    assert (wide.high - wide.low) > 4 * (narrow.high - narrow.low)
    # Independent sets: a set's draw moves only its half of the mean.
    one = seeds_and_queries_gain([tight])
    assert (narrow.high - narrow.low) < (one.high - one.low)
    hits = rng.random(n) < 0.7
    reference = rng.random(n) < 0.6
    single = seeds_and_queries_gain([(hits.astype(float) - reference)[None]], resamples=20_000)
    plain = paired_gain(hits, reference, resamples=20_000)
    assert abs(single.gain - plain.gain) < 1e-9
    assert abs(single.low - plain.low) < 0.6 and abs(single.high - plain.high) < 0.6
    with pytest.raises(ValueError):
        seeds_and_queries_gain([np.zeros(5)])
