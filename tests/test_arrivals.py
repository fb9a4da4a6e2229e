"""The arrival process: Poisson arrivals thinned by the inlet's dead time, against their analytic statistics; the
sample drawn a chunk at a time, read in any order, holding a few chunks' cells whatever its length."""

import math

import numpy as np
import pytest
from scipy import stats

from sim.model import arrivals as arrivals_module
from sim.model.arrivals import Arrivals, dead_time_acceptance, offer, schedule


def test_admitted_gaps_follow_the_shifted_exponential_and_rejections_the_dead_time_law():
    rate, dead = 1000.0, 0.5e-3
    sample = offer(Arrivals(count=20_000, mix=(("RBC", 0.9), ("melanoma", 0.1)), rate=rate, process="poisson",
                            min_spacing=dead), np.random.default_rng(11))
    gaps = np.diff([t for t, _ in sample.admitted])
    # the admitted gaps are d + Exp(rate) exactly (memorylessness): Kolmogorov-Smirnov at the 1 % level
    assert stats.kstest(gaps, stats.expon(loc=dead, scale=1 / rate).cdf).pvalue > 0.01
    assert gaps.min() >= dead
    # a cell is admitted with probability 1 / (1 + rate d) (non-paralysable dead time), within 3 standard errors
    admitted = len(sample.admitted) / 20_000
    expected = dead_time_acceptance(rate, dead)
    assert abs(admitted - expected) < 3 * math.sqrt(expected * (1 - expected) / 20_000)
    # types are thinned independently of times: the rejected share of targets is the same
    targets = [n for _, n in sample.admitted].count("melanoma")
    rejected_targets = [n for _, n in sample.rejected].count("melanoma")
    share = targets / (targets + rejected_targets)
    assert abs(share - expected) < 3 * math.sqrt(expected * (1 - expected) / (targets + rejected_targets))


def test_the_gap_histogram_matches_its_density():
    rate, dead = 2000.0, 0.3e-3
    sample = offer(Arrivals(count=50_000, mix=(("RBC", 1.0),), rate=rate, process="poisson", min_spacing=dead),
                   np.random.default_rng(5))
    gaps = np.diff([t for t, _ in sample.admitted])
    edges = dead + np.linspace(0.0, 3 / rate, 16)
    counts, _ = np.histogram(gaps, bins=edges)
    expected = len(gaps) * np.diff(stats.expon(loc=dead, scale=1 / rate).cdf(edges))
    chi2 = float(np.sum((counts - expected) ** 2 / expected))
    assert chi2 < stats.chi2(len(counts) - 1).ppf(0.999), chi2


def test_regular_arrivals_keep_their_rate_and_refuse_to_overlap():
    sample = offer(Arrivals(count=5, mix=(("RBC", 1.0),), rate=1000.0, min_spacing=0.5e-3), np.random.default_rng(0))
    assert np.allclose(np.diff([t for t, _ in sample.admitted]), 1e-3) and sample.rejected == []
    with pytest.raises(ValueError, match="closer than the minimum spacing"):
        Arrivals(count=5, mix=(("RBC", 1.0),), rate=3000.0, min_spacing=0.5e-3)


@pytest.mark.parametrize("fields, words", [
    ({"rate": math.nan}, "rate must be positive"),
    ({"rate": math.inf}, "rate must be positive"),
    ({"min_spacing": math.nan}, "min_spacing"),
    ({"mix": (("RBC", math.nan),)}, "finite non-negative weights"),
    ({"count": 10**9}, "at most"),
])
def test_bad_arrivals_are_refused(fields, words):
    base = {"count": 5, "mix": (("RBC", 1.0),), "process": "poisson"}
    with pytest.raises(ValueError, match=words):
        Arrivals(**{**base, **fields})


def _dead_time_rule_holds(sample, dead: float) -> bool:
    """Every offered cell, in time order, is admitted exactly when it comes at least ``dead`` after the last admitted
    one (a non-paralysable dead time), across the chunks' seams."""
    merged = sorted([(t, 1) for t, _ in sample.admitted] + [(t, 0) for t, _ in sample.rejected])
    free = -math.inf
    for t, admitted in merged:
        if (t >= free) != bool(admitted):
            return False
        free = t + dead if admitted else free
    return True


@pytest.mark.parametrize("chunk", [None, 97, 1000])
def test_a_sample_drawn_a_chunk_at_a_time_keeps_the_dead_time_across_chunks_and_reads_the_same_in_any_order(chunk):
    arrivals = Arrivals(count=5000, mix=(("RBC", 0.7), ("melanoma", 0.3)), rate=3000.0, process="poisson",
                        min_spacing=0.4e-3)
    sample = offer(arrivals, np.random.default_rng(11), chunk)
    admitted, rejected = list(sample.admitted), list(sample.rejected)
    assert len(admitted) + len(rejected) == 5000 and len(rejected) > 1000
    assert _dead_time_rule_holds(sample, arrivals.min_spacing)
    times = [t for t, _ in admitted + rejected]
    assert min(times) == 0.0 and len(set(times)) == 5000
    # the counts kept as running totals are those of the cells
    names = [name for _, name in admitted + rejected]
    assert sample.offered == {name: names.count(name) for name in ("RBC", "melanoma")}
    for time in (0.0, 0.3, 0.777, 1.0, math.inf):
        due = [name for t, name in rejected if t <= time]
        assert sample.rejected.counts(time) == {name: due.count(name) for name in set(due)}
    # drawn again when read: any order, any stretch, the same cells (a fresh sample of the same seed read backwards)
    again = offer(arrivals, np.random.default_rng(11), chunk)
    assert [again.admitted[i] for i in reversed(range(len(admitted)))] == admitted[::-1]
    assert again.admitted[-3:] == admitted[-3:] and again.admitted[7] == admitted[7] and again.rejected == rejected
    stretch_times, kinds = again.admitted.arrays(1234, 2345)
    assert list(zip(stretch_times.tolist(), [again.admitted.names[k] for k in kinds])) == admitted[1234:2345]
    assert kinds.itemsize == 1
    # same seed, same sample; another seed, another
    assert offer(arrivals, np.random.default_rng(12), chunk).admitted != admitted


def test_regular_and_explicit_samples_read_through_their_chunks():
    regular = offer(Arrivals(count=1000, mix=(("RBC", 0.5), ("melanoma", 0.5)), rate=1000.0, first=0.25),
                    np.random.default_rng(1), chunk=64)
    assert len(regular.rejected) == 0
    assert np.allclose([t for t, _ in regular.admitted], 0.25 + np.arange(1000) * 1e-3, rtol=0, atol=1e-12)
    cells = tuple(["RBC", "melanoma", "RBC"] * 100)
    explicit = schedule(Arrivals(cells=cells, rate=500.0), np.random.default_rng(0))
    assert [name for _, name in explicit] == list(cells)


def test_what_a_sample_holds_does_not_grow_with_its_length(monkeypatch):
    """Ten times the cells offered: the arrays a sample holds (its last chunks drawn, running counts per chunk) grow
    by the chunks' counts only, far below a byte per offered cell, after reading it through."""
    monkeypatch.setattr(arrivals_module, "CHUNK", 2048)

    def held(count):
        sample = offer(Arrivals(count=count, mix=(("RBC", 0.9), ("melanoma", 0.1)), rate=2000.0,
                                process="poisson"), np.random.default_rng(3))
        for start in range(0, len(sample.admitted), 5000):           # read through, as a run does
            sample.admitted.arrays(start, start + 5000)
        drawn = sum(array.nbytes for cells in sample._drawn.values() for side in cells for array in side)
        return drawn + sum(getattr(sample, name).nbytes for name in ("_origin", "_free", "_first", "_before",
                                                                      "_types")), len(sample._states)

    (small, _), (large, large_states) = held(20_000), held(200_000)
    assert large - small < 0.05 * (200_000 - 20_000)          # a per-offered-cell array would be >= 1 byte a cell
    assert large_states <= 200_000 / 2048 + 1
