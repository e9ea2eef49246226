"""The many-target steps (issue 16, covnet/covariance_control/targets.py): the paper scenario
through them is today's run bit for bit; the dwell's draws; the updates without and with
clutter; the decision for one and for several targets."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import yaml

from covnet.core.allocation.assignment import allocate_assignments_exhaustive
from covnet.core.allocation.exact import allocate
from covnet.core.ekf import ekf_update
from covnet.core.gaussian import Gaussian
from covnet.covariance_control import targets
from covnet.covariance_control.config import from_dict, load
from covnet.covariance_control.model import build_model, measure
from covnet.covariance_control.simulate import run_metric, run_targets

ROOT = Path(__file__).resolve().parents[2]
MULTI = ROOT / "configs" / "multitarget.yaml"


@pytest.fixture(scope="module")
def multi():
    return load(MULTI)


def small(scans: int = 12, **changes):
    """The shipped scenario cut short (no manoeuvre), with ``changes`` on top."""
    data = yaml.safe_load(MULTI.read_text())
    data["scans"] = scans
    data["targets"][2].pop("manoeuvres")
    data.update(changes)
    return data


def test_the_paper_through_the_many_target_steps_is_todays_run(paper):
    """T = 1, position sensors, pd 1, no clutter: the same subsets, values, estimates and
    covariances, bit for bit, as covnet run's single-target loop."""
    a = run_metric(paper, "spectral")
    b = run_targets(paper, "spectral")
    assert np.array_equal(a.enabled, b.enabled)
    assert np.array_equal(a.value, b.value)
    assert np.array_equal(a.x_est, b.x_est[0])
    assert np.array_equal(a.P_post, b.P_post[0])
    assert np.array_equal(a.P_pred, b.P_pred[0])
    assert np.array_equal(a.nees, b.nees[0])
    assert (b.returns[b.enabled] == 1).all() and b.used[b.enabled].all()


def test_a_one_target_config_with_targets_is_the_paper(paper_path):
    """The paper written with ``targets:`` (one target, its schedule, position sensors) runs
    the same scans as the paper config."""
    raw = yaml.safe_load(paper_path.read_text())
    tg = raw.pop("target")
    raw["targets"] = [
        {
            "id": "T1",
            "initial_position_m": tg["initial_position_m"],
            "initial_velocity_mps": tg["initial_velocity_mps"],
            "accel_noise_std_mps2": tg["accel_noise_std_mps2"],
            "desired": raw.pop("desired"),
        }
    ]
    raw["scans"] = 30
    sc = from_dict(raw)
    paper = from_dict({**yaml.safe_load(paper_path.read_text()), "scans": 30})
    a, b = run_metric(paper, "svd"), run_targets(sc, "svd")
    assert np.array_equal(a.enabled, b.enabled)
    assert np.array_equal(a.x_est, b.x_est[0])


def test_position_dwell_is_the_paper_measurement(paper):
    tm = targets.build(paper)
    model = build_model(paper)
    x = np.array([1000.0, 400.0, -300.0, 2.0])
    for j in range(len(tm.sensors)):
        for k in (1, 7, 99):
            Z = targets.dwell(tm, j, k, x, None)
            assert Z.shape == (1, 2)
            assert np.array_equal(Z[0], measure(model, j, k, x))


def test_the_target_return_does_not_depend_on_pd_or_clutter(multi):
    """The noise is drawn first: the same target return with any pd or clutter, only whether
    it is reported changes; clutter lies in the window."""
    base = small()
    tm = targets.build(from_dict(base))
    preds = targets.predict_all(tm, targets.initial_estimates(tm))
    x = targets.truth_trajectories(tm)[0, 0]
    j = 4  # R1
    win = targets.window(tm, j, preds[0])
    assert win is not None
    quiet = copy.deepcopy(base)
    for s in quiet["sensors"]:
        s.update(pd=1.0, clutter_rate=0.0)
    tq = targets.build(from_dict(quiet))
    found = 0
    for k in range(1, 60):
        clean = targets.dwell(tq, j, k, x, None)
        assert clean.shape == (1, 2)
        Z = targets.dwell(tm, j, k, x, win)
        hit = [i for i in range(Z.shape[0]) if np.array_equal(Z[i], clean[0])]
        found += bool(hit)
        others = np.delete(Z, hit, axis=0)
        assert win.contains(others).all()
    assert 40 < found < 59  # pd 0.9


def test_an_update_without_clutter_is_the_plain_update(multi):
    data = small()
    for s in data["sensors"]:
        s["clutter_rate"] = 0.0
        s["pd"] = 1.0
    tm = targets.build(from_dict(data))
    prior = Gaussian(np.array([9000.0, 30.0, 2100.0, 100.0]), np.diag([400.0, 25.0, 400.0, 25.0]))
    x_true = np.array([9010.0, 31.0, 2090.0, 99.0])
    dec = targets.TargetDecision(
        (targets.OFF,) * 4 + (0,) + (targets.OFF,) * 3 + (0,) + (targets.OFF,) * 3,
        0.0, (0.0,), prior.P[None], 0, np.ones((12, 1), dtype=bool),
    )  # fmt: skip
    returns = {j: targets.dwell(tm, j, 3, x_true, None) for j in (4, 8)}
    (post,), (dwells,) = targets.fuse(tm, [prior], dec, returns, {})
    expect = ekf_update(prior, returns[4][0], tm.sensors[4]).posterior
    expect = ekf_update(expect, returns[8][0], tm.sensors[8]).posterior
    assert np.array_equal(post.x, expect.x) and np.array_equal(post.P, expect.P)
    assert [d.sensor for d in dwells] == [4, 8] and all(d.used for d in dwells)
    assert [d.dof for d in dwells] == [2, 1]


def test_a_miss_keeps_the_prior(multi):
    prior = Gaussian(np.array([9000.0, 30.0, 2100.0, 100.0]), np.diag([400.0, 25.0, 400.0, 25.0]))
    tm = targets.build(multi)  # with clutter: PDA of no returns
    post, d = targets._update_one(tm, 4, prior, np.zeros((0, 2)), targets.window(tm, 4, prior))
    assert np.array_equal(post.x, prior.x) and not d.used and d.nis is None
    data = small()
    for s in data["sensors"]:
        s["clutter_rate"] = 0.0
    tm = targets.build(from_dict(data))  # without: nothing to update with
    post, d = targets._update_one(tm, 4, prior, np.zeros((0, 2)), None)
    assert post is prior and not d.used and d.nis is None


def test_pda_with_clutter_gates_and_weights(multi):
    tm = targets.build(multi)
    prior = Gaussian(np.array([9000.0, 30.0, 2100.0, 100.0]), np.diag([400.0, 25.0, 400.0, 25.0]))
    win = targets.window(tm, 4, prior)
    far = win.center + 0.99 * win.half_width  # clutter at the window's edge: outside the gate
    z = tm.sensors[4].h(prior.x)
    post, d = targets._update_one(tm, 4, prior, np.array([far, z]), win)
    assert d.used and d.returns == 2 and d.nis == pytest.approx(0.0, abs=1e-12)
    assert np.trace(post.P) < np.trace(prior.P)


def test_decide_one_target_is_the_single_target_allocator(paper):
    tm = targets.build(paper)
    model = build_model(paper)
    preds = targets.predict_all(tm, targets.initial_estimates(tm))
    dec = targets.decide(tm, preds, 5, "abs_trace", frozenset({2}))
    ref = allocate(
        preds[0].P, model.gains, model.desired(5), "abs_trace",
        constraints=type(model.constraints)(excluded=frozenset({2})),
    )  # fmt: skip
    assert dec.subset == ref.subset and dec.value == ref.value
    assert 2 not in dec.subset


def test_decide_many_targets_is_the_exhaustive_reference(multi):
    """The decision for 3 targets is the plain enumeration's (on 8 of the sensors: 4^8)."""
    data = small(scans=5)
    data["sensors"] = data["sensors"][:8]
    tm = targets.build(from_dict(data))
    preds = targets.predict_all(tm, targets.initial_estimates(tm))
    dec = targets.decide(tm, preds, 2, "spectral")
    J, feas = targets.information(tm, preds)
    ref = allocate_assignments_exhaustive(
        np.array([g.P for g in preds]), J, np.array([t.desired(2) for t in tm.targets]),
        "spectral", [t.weight(2) for t in tm.targets], feas,
    )  # fmt: skip
    assert dec.assignment == ref.assignment and dec.value == ref.value


def test_failed_and_uncovered_sensors_stay_off(multi):
    tm = targets.build(multi)
    preds = targets.predict_all(tm, targets.initial_estimates(tm))
    dec = targets.decide(tm, preds, 1, "spectral", frozenset(range(8)))
    assert all(dec.assignment[j] == targets.OFF for j in range(8))
    for j, a in enumerate(dec.assignment):
        if a != targets.OFF:
            assert dec.feasible[j, a]
    everything = targets.decide(tm, preds, 1, "spectral", frozenset(range(12)))
    assert everything.subset == () and len(everything.values) == 3


def test_weights_and_schedules_per_target(multi):
    tm = targets.build(multi)
    t1 = tm.targets[0]
    assert t1.weight(50) == 1.0 and t1.weight(51) == 2.0
    assert t1.desired(50)[0, 0] == 200.0 and t1.desired(51)[0, 0] == 40.0
    assert tm.targets[2].weight(80) == 1.0


def test_usable_returns(multi):
    tm = targets.build(multi)
    R = tm.sensors[8].R
    assert targets.usable_returns(tm, 8, np.array([[0.5], [3.0]]), R)
    assert not targets.usable_returns(tm, 8, np.array([[4.0]]), R)  # not a bearing
    assert not targets.usable_returns(tm, 8, np.zeros((1, 2)), R)  # a radar's shape
    assert not targets.usable_returns(tm, 8, np.zeros((1, 1)), 2 * R)  # not its noise
    assert targets.usable_returns(tm, 8, np.zeros((0, 1)), R)


def test_windows_travel_as_vectors(multi):
    tm = targets.build(multi)
    preds = targets.predict_all(tm, targets.initial_estimates(tm))
    for j in (0, 4, 8):
        w = targets.window(tm, j, preds[1])
        back = targets.window_from_vec(tm, j, targets.window_vec(w))
        assert np.array_equal(back.center, w.center)
        assert np.array_equal(back.half_width, w.half_width)
        assert back.angle_mask == w.angle_mask
    with pytest.raises(ValueError):
        targets.window_from_vec(tm, 8, np.zeros(4))


def test_run_is_deterministic_for_a_seed():
    sc = from_dict(small(scans=8))
    a, b = run_targets(sc, "abs_trace"), run_targets(sc, "abs_trace")
    for f in ("assignment", "x_est", "P_post", "nees", "nis_sum", "returns"):
        assert np.array_equal(getattr(a, f), getattr(b, f)), f
    other = run_targets(from_dict({**small(scans=8), "seed": 7}), "abs_trace")
    assert not np.array_equal(a.x_est, other.x_est)


def _linear(scans: int = 20) -> dict:
    """The scenario's 4 position sensors with misses (pd 0.9) but no clutter and no range
    limit: every update a linear Kalman update."""
    data = small(scans)
    data["sensors"] = [
        {k: v for k, v in s.items() if k != "max_range_m"} | {"clutter_rate": 0.0}
        for s in data["sensors"]
        if s.get("model", "position") == "position"
    ]
    return data


def test_info_equals_central_for_linear_updates():
    """fusion.mode info for three targets: each sensor's own filter of every target, the
    centre's information fusion; with linear updates (position sensors, misses, no clutter)
    the central filter to rounding, and the same assignments."""
    central = run_targets(from_dict(_linear()), "abs_trace")
    info = run_targets(from_dict({**_linear(), "fusion": {"mode": "info"}}), "abs_trace")
    np.testing.assert_array_equal(info.assignment, central.assignment)
    np.testing.assert_allclose(info.x_est, central.x_est, rtol=0, atol=1e-9 * 2e4)
    np.testing.assert_allclose(info.P_post, central.P_post, rtol=1e-9, atol=1e-9)
    assert (central.returns[central.enabled] <= 1).all()
    assert not central.used[central.enabled].all()  # some misses


def test_info_with_radars_and_clutter_runs_and_is_close_to_central():
    """With EKF linearisation at each sensor's own estimate and PDA in clutter, information
    fusion is an approximation: it runs, tracks every target, and the centre sees no NIS."""
    central = run_targets(from_dict(small(20)), "abs_trace")
    info = run_targets(from_dict({**small(20), "fusion": {"mode": "info"}}), "abs_trace")
    tm = targets.build(from_dict(small(20)))
    truth = targets.truth_trajectories(tm)
    for r in (central, info):
        err = np.hypot(*(r.x_est - truth)[:, :, [0, 2]].transpose(2, 0, 1))
        assert err.max() < 150.0
    assert info.nis_n.sum() == 0 and central.nis_n.sum() > 0


def test_detection_modes_scale_the_information():
    """allocation.detection: expected scales HᵀR⁻¹H by pd, ignore by 1, pda by the PDAF's
    q₂ (below pd · P_G in clutter)."""
    Js = {}
    for mode in ("ignore", "expected", "pda"):
        data = small(4)
        data["allocation"]["detection"] = mode
        tm = targets.build(from_dict(data))
        preds = targets.predict_all(tm, targets.initial_estimates(tm))
        Js[mode], feas = targets.information(tm, preds)
    on = feas[4, 0]
    assert on
    ref = Js["ignore"][4, 0]
    nz = np.abs(ref) > 0
    ratio_e = Js["expected"][4, 0][nz] / ref[nz]
    ratio_p = Js["pda"][4, 0][nz] / ref[nz]
    np.testing.assert_allclose(ratio_e, 0.9)
    q2 = float(ratio_p[0])
    assert 0.0 < q2 < 0.9 * 0.99
    np.testing.assert_allclose(ratio_p, q2)
