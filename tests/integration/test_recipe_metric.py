"""README "Adding a metric", executed: a new metric (the nuclear norm of the difference, without
any bound) is one :class:`~covnet.core.metrics.Metric` entry in ``METRICS`` (registered here in
a temporary registry: the test's own ``monkeypatch``); a config naming it runs through ``covnet
run``, a lockstep network run (equal bit for bit) and ``covnet replay``; the property tests over
every registered metric cover it; and the config refuses, in the search entry's words, the
searches that need a bound it does not have."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from recipe_harness import run_all_three, write_config

from covnet.config import ConfigError
from covnet.core.metrics import METRICS, Metric
from covnet.covariance_control.config import load

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "property"))
import test_metric_axioms as axioms  # noqa: E402


def nuclear(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Nuclear norm of the difference: ``f = ||A - B||_* = sum_k |λ_k(A - B)|``."""
    w = np.linalg.eigvalsh(np.asarray(A, dtype=np.float64) - np.asarray(B, dtype=np.float64))
    return np.abs(w).sum(axis=-1)


NUCLEAR = Metric("nuclear", nuclear)


@pytest.fixture
def registered(monkeypatch):
    monkeypatch.setitem(METRICS, "nuclear", NUCLEAR)  # restored after the test


def test_a_new_metric_runs_everywhere(registered, tmp_path):
    cfg = write_config(tmp_path, {"metrics": ["nuclear"]})
    run_all_three(cfg, tmp_path, "nuclear")


def test_the_property_tests_cover_the_new_metric(registered):
    assert "nuclear" in sorted(METRICS)
    axioms.test_nonnegative(name="nuclear")
    axioms.test_zero_on_identical(name="nuclear")
    axioms.test_symmetric(name="nuclear")
    axioms.test_batched_equals_one_at_a_time(name="nuclear")


def test_the_searches_that_need_a_bound_refuse_it(registered, tmp_path):
    cfg = write_config(tmp_path, {"metrics": ["nuclear"], "search": "bounded"})
    with pytest.raises(ConfigError) as err:
        load(cfg)
    assert any(
        p == "allocation.search" and "branch and bound stopped" in m and "'nuclear' has none" in m
        for p, m in err.value.problems
    ), err.value.problems
    # greedy needs none: its certified lower bound is then 0 (every metric is >= 0)
    load(write_config(tmp_path, {"metrics": ["nuclear"], "search": "greedy"}))


def test_exact_beyond_what_enumeration_holds_is_refused_for_it(registered, tmp_path):
    """``search: exact`` with a metric without a bound enumerates every subset: on 64 sensors
    ``covnet run`` asked for 32 PiB and died with a traceback.  The config refuses it beyond
    ``AUTO_EXACT_MAX`` candidate sensors, naming the metric and the way out."""
    import yaml

    from covnet.covariance_control.searches import AUTO_EXACT_MAX

    large = Path(__file__).resolve().parents[2] / "configs" / "large.yaml"
    data = yaml.safe_load(large.read_text())
    data["allocation"] = {"metrics": ["nuclear"], "search": "exact"}
    path = tmp_path / "large.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError) as err:
        load(path)
    n = len(data["sensors"])
    assert n > AUTO_EXACT_MAX
    assert (
        "allocation.search",
        f"exact with {n} candidate sensors: metric 'nuclear' has no interval bound (its METRICS "
        f"entry's interval_bound is None), so every subset (2^{n}) would be evaluated; at most "
        f"{AUTO_EXACT_MAX} candidate sensors for it: choose search: greedy, or exclude sensors",
    ) in err.value.problems
    # the same network with greedy, or exact with the built-in metrics, is a config
    data["allocation"]["search"] = "greedy"
    path.write_text(yaml.safe_dump(data))
    load(path)
    data["allocation"] = {"metrics": ["spectral"], "search": "exact"}
    path.write_text(yaml.safe_dump(data))
    load(path)
