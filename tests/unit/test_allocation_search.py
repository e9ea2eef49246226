"""``allocation.search`` (issue 17): the config, the decision the runners and the manager make
through it, and what it reports (``value``, ``lower_bound``, ``gap`` per scan)."""

from __future__ import annotations

import copy
import itertools
import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from covnet.config import ConfigError
from covnet.core.allocation.constraints import Constraints
from covnet.core.allocation.exact import allocate, allocate_exhaustive, prepare
from covnet.core.allocation.search import allocate_bnb
from covnet.core.allocation.search_problem import gap_from_nothing
from covnet.core.metrics import spectral
from covnet.covariance_control.config import (
    AUTO_EXACT_MAX,
    AUTO_NODE_LIMIT,
    BOUNDED_GAP,
    config_hash,
    from_dict,
    normalised,
)
from covnet.covariance_control.model import (
    FAST_PATH_MAX,
    build_model,
    decide,
    feasible_count,
)
from covnet.covariance_control.results import write_run
from covnet.covariance_control.simulate import run_metric, shared_trajectory

LARGE = Path(__file__).resolve().parents[2] / "configs" / "large.yaml"


@pytest.fixture()
def raw(paper_path):
    return yaml.safe_load(paper_path.read_text())


def _large(n_sensors: int, scans: int, **allocation) -> dict:
    """The first ``n_sensors`` sensors of configs/large.yaml (the paper's families, scaled)."""
    d = yaml.safe_load(LARGE.read_text())
    d["sensors"] = d["sensors"][:n_sensors]
    d["scans"] = scans
    d["allocation"] = {"metrics": ["spectral"], **allocation}
    return d


def _problems(data) -> list[tuple[str, str]]:
    with pytest.raises(ConfigError) as info:
        from_dict(data, "test.yaml")
    return info.value.problems


# ---- the config ------------------------------------------------------------------------------


def test_default_is_auto_and_leaves_the_hash_alone(paper, raw):
    assert paper.allocation.search == "auto"
    assert (paper.allocation.gap, paper.allocation.time_limit_s) == (None, None)
    al = normalised(paper)["allocation"]
    assert not {"search", "gap", "time_limit_s", "node_limit"} & set(al)
    explicit = copy.deepcopy(raw)
    explicit["allocation"]["search"] = "auto"
    assert config_hash(from_dict(explicit)) == config_hash(paper)
    model = build_model(paper)
    assert model.search_mode == "exact" and not model.reports_gap


def test_search_options_are_recorded(raw):
    raw["allocation"].update(search="bounded", gap=0.02, time_limit_s=0.5, node_limit=1000)
    sc = from_dict(raw)
    al = normalised(sc)["allocation"]
    assert (al["search"], al["gap"], al["time_limit_s"], al["node_limit"]) == (
        "bounded",
        0.02,
        0.5,
        1000,
    )
    m = build_model(sc)
    assert m.search_mode == "bounded" and m.search.bounded_options() == (0.02, 0.5, 1000)


def test_auto_is_exact_up_to_its_size_then_bounded():
    assert build_model(from_dict(_large(AUTO_EXACT_MAX, 1))).search_mode == "exact"
    big = build_model(from_dict(_large(AUTO_EXACT_MAX + 1, 1)))
    assert big.search_mode == "bounded" and big.reports_gap
    assert big.search.bounded_options() == (BOUNDED_GAP, None, AUTO_NODE_LIMIT)
    # excluded sensors are not candidates
    d = _large(AUTO_EXACT_MAX + 1, 1, excluded=["S1.1"])
    assert build_model(from_dict(d)).search_mode == "exact"


@pytest.mark.parametrize(
    "change,path,text",
    [
        ({"search": "fast"}, "allocation.search", "'auto', 'exact', 'bounded' or 'greedy'"),
        ({"search": "bounded", "gap": 1.5}, "allocation.gap", "must be in [0, 1)"),
        ({"search": "bounded", "gap": -0.01}, "allocation.gap", "must be in [0, 1)"),
        ({"search": "bounded", "gap": "1%"}, "allocation.gap", "valid number"),
        ({"search": "bounded", "time_limit_s": 0.0}, "allocation.time_limit_s", "must be > 0"),
        ({"search": "bounded", "node_limit": 0}, "allocation.node_limit", "must be >= 1"),
        ({"search": "bounded", "node_limit": 2.5}, "allocation.node_limit", "valid integer"),
        ({"search": "exact", "gap": 0.01}, "allocation.gap", "only used with search: bounded"),
        (
            {"search": "greedy", "time_limit_s": 1.0},
            "allocation.time_limit_s",
            "only used with search: bounded",
        ),
    ],
)
def test_bad_search_values_name_their_path(raw, change, path, text):
    raw["allocation"].update(change)
    problems = _problems(raw)
    assert any(p == path and text in m for p, m in problems), problems


@pytest.mark.parametrize("mode", ["ci", "peer"])
def test_bounded_needs_an_information_form_centre(raw, mode):
    raw["allocation"]["search"] = "bounded"
    raw["fusion"] = {"mode": mode}
    problems = _problems(raw)
    assert any(p == "allocation.search" and "information form" in m for p, m in problems)


def test_feasible_count_matches_enumeration():
    c = Constraints(excluded=frozenset({0}), required=frozenset({2}), max_active=4)
    n = sum(1 for k in range(1, 5) for s in itertools.combinations(range(1, 9), k) if 2 in s)
    assert feasible_count(9, c) == n
    assert feasible_count(8, Constraints()) == 255


# ---- the decisions ---------------------------------------------------------------------------


def test_exact_beyond_the_fast_path_is_the_exhaustive_search():
    """Over FAST_PATH_MAX candidates ``exact`` is branch and bound: the fast path's (hence the
    exhaustive search's) subset, value and P, bit for bit, at every scan of a run."""
    N = FAST_PATH_MAX + 2
    sc = from_dict(_large(N, 8, search="exact"))
    model = build_model(sc)
    plan = prepare(model.gains)
    for metric in ("spectral", "abs_trace"):
        run = run_metric(sc, metric)
        assert run.lower_bound is None and run.gap is None
        for i in range(sc.scans):
            ref = allocate(run.P_pred[i], plan, model.desired(i + 1), metric)
            assert tuple(np.flatnonzero(run.enabled[i])) == ref.subset
            assert run.value[i] == ref.value


def test_exact_branch_and_bound_decision_equals_allocate_exhaustive():
    N = FAST_PATH_MAX + 2
    sc = from_dict(_large(N, 3, search="exact", max_active=3))
    model = build_model(sc)
    run = run_metric(sc, "spectral")
    c = Constraints(excluded=frozenset({4}), max_active=3)
    for i, metric in itertools.product(range(3), ("spectral", "svd", "logdet")):
        P_pred, P_d = run.P_pred[i], model.desired(i + 1)
        got = decide(model, P_pred, i + 1, metric, unavailable=frozenset({4}))
        ref = allocate_exhaustive(P_pred, model.gains, P_d, metric, c)
        assert (got.subset, got.value) == (ref.subset, ref.value)
        assert np.array_equal(got.P, ref.P)
        assert got.lower_bound is None and got.n_feasible == ref.n_feasible


@pytest.mark.parametrize("metric", ["spectral", "kl"])
def test_bounded_on_32_sensors_reports_a_gap_within_the_requested(metric):
    sc = from_dict(_large(32, 20, search="bounded", gap=0.01))
    run = run_metric(sc, metric)
    assert run.lower_bound is not None and run.gap is not None
    assert np.all(run.gap <= 0.01)
    assert np.all(run.lower_bound <= run.value)
    assert np.array_equal(run.gap, (run.value - run.lower_bound) / np.abs(run.value))
    # the bound is certified: below the exact optimum at a few scans
    model = build_model(sc)
    for i in (5, 9, 19):  # (scans 1-3 are near ties: an exact search there takes long)
        P_d = model.desired(i + 1)
        opt = allocate_bnb(run.P_pred[i], model.gains, P_d, metric)
        assert run.lower_bound[i] <= opt.value <= run.value[i]
        assert run.value[i] * (1 - 0.01) <= opt.value * (1 + 1e-12)


def test_greedy_on_40_sensors_reports_its_certified_gap():
    sc = from_dict(_large(40, 15, search="greedy"))
    run = run_metric(sc, "spectral")
    assert run.gap is not None and run.lower_bound is not None
    assert np.all(np.isfinite(run.gap)) and np.all((run.gap >= 0) & (run.gap <= 1))
    assert np.all(run.lower_bound <= run.value)


def test_bounded_with_a_node_limit_is_deterministic():
    sc = from_dict(_large(40, 6, search="bounded", gap=0.0, node_limit=500))
    a, b = run_metric(sc, "svd"), run_metric(sc, "svd")
    assert np.array_equal(a.enabled, b.enabled) and np.array_equal(a.value, b.value)
    assert np.array_equal(a.gap, b.gap)


def test_gap_from_nothing_elementwise():
    """``(value - L) / (nothing - value)``; 0 without a gap, inf where the decision does no
    better than doing nothing, NaN where no bound was reported; scalars too."""
    v = np.array([2.0, 2.0, 5.0, 5.0, 3.0])
    lo = np.array([1.0, 2.0, 4.0, np.nan, 3.5])
    no = np.array([6.0, 6.0, 5.0, 9.0, 8.0])
    g = gap_from_nothing(v, lo, no)
    assert g[0] == 0.25 and g[1] == 0.0 and g[2] == np.inf and np.isnan(g[3]) and g[4] == 0.0
    assert float(gap_from_nothing(2.0, 1.0, 6.0)) == 0.25


def test_summary_holds_value_lower_bound_and_gap(tmp_path):
    sc = from_dict(_large(34, 8, search="greedy"))
    run = run_metric(sc, "spectral")
    traj = shared_trajectory(build_model(sc))
    summary = write_run(tmp_path, sc, traj, {"spectral": run})
    blk = summary["metrics"]["spectral"]
    assert blk["value"] == run.value.tolist()
    assert blk["lower_bound"] == run.lower_bound.tolist()
    assert blk["gap"] == run.gap.tolist()
    assert blk["gap_worst"] == float(run.gap.max())
    assert blk["gap_median"] == float(np.median(run.gap))
    # relative to the distance from doing nothing: the metric of each scan's prediction
    nothing = np.array([spectral(P, D) for P, D in zip(run.P_pred, traj.P_d, strict=True)])
    want = (run.value - run.lower_bound) / (nothing - run.value)
    want[run.value == run.lower_bound] = 0.0
    assert blk["gap_nothing"] == pytest.approx(want.tolist(), rel=1e-12, abs=0.0)
    assert blk["gap_nothing_worst"] == pytest.approx(float(want.max()), rel=1e-12)
    assert blk["gap_nothing_median"] == pytest.approx(float(np.median(want)), rel=1e-12)
    assert np.all(nothing > run.value)  # every decision improves on doing nothing here
    on_disk = json.loads((tmp_path / "summary.json").read_text())  # strict JSON, no NaN
    assert on_disk["metrics"]["spectral"]["gap"] == blk["gap"]
    arrays = np.load(tmp_path / "arrays.npz")
    assert np.array_equal(arrays["gap.spectral"], run.gap)


def test_an_exact_summary_has_no_gap(paper, tmp_path):
    sc = from_dict({**normalised(paper), "scans": 3})
    run = run_metric(sc, "spectral")
    summary = write_run(tmp_path, sc, shared_trajectory(build_model(sc)), {"spectral": run})
    assert not {"lower_bound", "gap", "gap_median", "gap_nothing"} & set(
        summary["metrics"]["spectral"]
    )
    assert "gap.spectral" not in np.load(tmp_path / "arrays.npz")
