"""``covnet bench search`` says per row whether issue 29's certificate goal is met, in which
measure (gap relative to the value, relative to doing nothing), and whether the worst decision
fits the time too."""

from __future__ import annotations

import pytest

from covnet.covariance_control.bench_search import CERT_GOALS, cert_goal, format_row, meets_goal


def _row(N: int, med: float, worst: float, gap: float, gap_nothing: float) -> dict:
    return {
        "search": "bounded",
        "metric": "spectral",
        "n_sensors": N,
        "median_s": med,
        "worst_s": worst,
        "gap_median": gap,
        "gap_nothing_median": gap_nothing,
    }


def test_goal_per_size():
    assert CERT_GOALS[0] == (100, 0.01, 0.05)
    assert cert_goal(64) == cert_goal(100) == (0.01, 0.05)
    assert cert_goal(101) == cert_goal(1000) == cert_goal(5000) == (0.05, 2.0)


@pytest.mark.parametrize(
    ("row", "meets", "worst_within"),
    [
        (_row(100, 0.04, 0.049, 0.009, 0.002), "both", True),
        (_row(100, 0.04, 0.06, 0.02, 0.01), "nothing", False),  # 1 % itself meets it
        (_row(100, 0.04, 0.05, 0.005, 0.3), "value", True),
        (_row(100, 0.051, 0.06, 0.0, 0.0), "no", False),  # too slow: no gap helps
        (_row(1000, 1.9, 2.1, 0.049, 0.2), "value", False),
        (_row(1000, 1.5, 1.6, 0.06, 0.06), "no", True),
    ],
)
def test_meets_goal(row, meets, worst_within):
    m = meets_goal(row)
    assert m["meets"] == meets and m["worst_within"] is worst_within
    assert m["meets_value"] is (meets in ("both", "value"))
    assert m["meets_nothing"] is (meets in ("both", "nothing"))
    line = format_row({**row, **m})
    assert line.split()[-2:] == [meets, str(worst_within)]
