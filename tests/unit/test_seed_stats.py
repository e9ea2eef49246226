"""Intervals over seeds stay in the range of their quantity (an RMSE's lower end reached -54 m
in ``covnet sweep``, a deadline-miss rate's upper end 1.02, a passive share 1.05, where
``covnet mc`` stopped its intervals at 0), printed as ``mean [lo, hi]`` once cut; with one seed
a per-scan curve has no interval (it had the mean as both ends)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats as sps

from covnet.batches.stats import (
    NONNEGATIVE,
    SHARE,
    per_scan_interval,
    plus_minus,
    seed_stats,
)
from covnet.covariance_control.sweep import SPREAD


def _t(v):
    v = np.asarray(v, dtype=float)
    lo, hi = sps.t.interval(0.95, v.size - 1, loc=v.mean(), scale=sps.sem(v))
    return lo, hi


def test_the_t_interval_cut_to_the_quantitys_range():
    rmse = [0.2, 9.0, 0.4]  # a lost seed: the t interval reaches far below 0
    lo, hi = _t(rmse)
    assert lo < 0
    assert (seed_stats(rmse)["ci_lo"], seed_stats(rmse)["ci_hi"]) == pytest.approx((lo, hi))
    cut = seed_stats(rmse, NONNEGATIVE)
    assert cut["ci_lo"] == 0.0 and cut["ci_hi"] == pytest.approx(hi)
    miss = [1.0, 0.97, 1.0]
    lo, hi = _t(miss)
    assert hi > 1
    cut = seed_stats(miss, SHARE)
    assert cut["ci_hi"] == 1.0 and cut["ci_lo"] == pytest.approx(lo)
    assert cut["mean"] == pytest.approx(np.mean(miss)) and cut["std"] == pytest.approx(
        np.std(miss, ddof=1)
    )


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(0.0, 1.0), min_size=2, max_size=8))
def test_a_shares_interval_holds_its_mean_and_stays_in_0_1(values):
    s = seed_stats(values, SHARE)
    assert 0.0 <= s["ci_lo"] <= s["mean"] + 1e-12
    assert s["mean"] - 1e-12 <= s["ci_hi"] <= 1.0
    lo, hi = _t(values) if np.std(values) > 0 else (np.mean(values),) * 2
    assert s["ci_lo"] == pytest.approx(max(lo, 0.0), abs=1e-12)
    assert s["ci_hi"] == pytest.approx(min(hi, 1.0), abs=1e-12)


def test_printed_as_plus_minus_when_centred_and_as_its_ends_once_cut():
    assert plus_minus(5.0, 4.0, 6.0) == "5.00 ± 1.00"
    assert plus_minus(5.0, 4.0, 6.0, ".1f", "±") == "5.0±1.0"
    assert plus_minus(0.5, 0.0, 1.4) == "0.50 [0.00, 1.40]"
    assert plus_minus(0.5, None, None) == "0.50"


def test_the_sweeps_rates_are_shares_and_its_counts_nonnegative():
    assert SPREAD == {
        "allocation_rate": SHARE,
        "deadline_miss_rate": SHARE,
        "late": NONNEGATIVE,
        "lost": NONNEGATIVE,
    }


def test_one_seed_has_no_per_scan_interval():
    one = per_scan_interval([[3.0, 2.0]], bounds=NONNEGATIVE)
    assert one == {"mean": [3.0, 2.0], "ci95_low": None, "ci95_high": None}
    two = per_scan_interval([[3.0, 2.0], [5.0, 2.0]], bounds=NONNEGATIVE)
    assert two["ci95_low"][1] == two["ci95_high"][1] == 2.0 and two["ci95_low"][0] == 0.0


def test_the_mc_summary_of_a_rate_stays_within_0_1():
    """``covnet mc``'s scalars stopped at 0; a rate's upper end could pass 1 (the allocation
    rate's, surveillance's search share)."""
    from covnet.batches.stats import interval

    rates = [1.0, 0.97, 1.0]
    assert _t(rates)[1] > 1
    assert interval(rates, bounds=SHARE)["ci95"] == [pytest.approx(_t(rates)[0]), 1.0]
    assert interval([0.2, 9.0, 0.4], bounds=NONNEGATIVE)["ci95"][0] == 0.0
    assert interval([0.2, 9.0, 0.4])["ci95"][0] < 0
