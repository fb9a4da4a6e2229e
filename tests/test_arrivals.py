"""The arrival process: Poisson arrivals thinned by the inlet's dead time, against their analytic statistics."""

import math

import numpy as np
import pytest
from scipy import stats

from sim.model.arrivals import Arrivals, dead_time_acceptance, offer


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
