"""``covnet.batches.stats.median`` is ``numpy.median`` bit for bit (it only avoids importing
numpy.ma), and
the model's cached noise factors draw the same measurements as factoring ``R`` every scan."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from covnet.batches.stats import median
from covnet.core import streams
from covnet.core.sensing import measure
from covnet.covariance_control.config import load
from covnet.covariance_control.model import build_model
from covnet.covariance_control.model import measure as model_measure

# beyond 1e300 the sum of the two middle values can overflow, and numpy's own mean warns
floats = st.floats(-1e300, 1e300, allow_nan=False, allow_infinity=False, width=64)


@given(st.lists(floats, min_size=1, max_size=40))
def test_median_is_numpys_bit_for_bit(values):
    assert median(values) == float(np.median(values))


@given(st.lists(st.integers(0, 10**9), min_size=1, max_size=40))
def test_median_of_counts_is_numpys(values):
    assert median(np.array(values)) == float(np.median(np.array(values)))


def test_median_of_nothing_or_nan_is_nan():
    assert math.isnan(median([]))
    assert math.isnan(median([1.0, float("nan"), 2.0]))


def test_the_cached_noise_factor_draws_what_factoring_r_each_scan_draws():
    model = build_model(load("configs/paper.yaml"))
    x = np.array([1000.0, 10.0, -500.0, 5.0])
    for j in range(len(model.sensor_ids)):
        for k in (0, 1, 57):
            rng = streams.sensor_stream(model.seed, j, k)
            expected = measure(model.H, model.R[j], x, rng)
            assert model_measure(model, j, k, x).tobytes() == expected.tobytes()
