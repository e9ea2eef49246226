"""JPDA: one track per cluster is the PDA; the exact marginals against a plain brute force."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from covnet.core.association import gate, gate_threshold, pda_update
from covnet.core.ekf import predict_measurement
from covnet.core.gaussian import Gaussian
from covnet.core.sensor_models import PositionModel, RangeBearingModel
from covnet.core.surveillance.jpda import clusters_of, jpda_update, track_gate

POS = PositionModel(sigma_x=10.0, sigma_y=10.0, rho=0.0, pd=0.9, clutter_rate=1.0)


def _prior(x: float, y: float, sigma: float = 30.0) -> Gaussian:
    return Gaussian(np.array([x, 5.0, y, -3.0]), np.diag([sigma**2, 25.0, sigma**2, 25.0]))


def _brute_force(priors, Z, model, lam, pds, pg):
    """Every map track -> {miss} ∪ rows over ALL tracks and ALL rows, feasible ones weighted by
    the plain product of the module docstring (linear space); marginals per track as a dict."""
    M = Z.shape[0]
    preds = [predict_measurement(p, model) for p in priors]
    gamma = gate_threshold(model.dim_z, pg)
    lik = np.zeros((len(priors), M))
    gated = np.zeros((len(priors), M), dtype=bool)
    for t, pr in enumerate(preds):
        for i in range(M):
            nu = pr.innovations(Z[i])
            d2 = float(nu @ np.linalg.solve(pr.S, nu))
            gated[t, i] = d2 <= gamma and pds[t] > 0
            lik[t, i] = math.exp(-0.5 * d2) / math.sqrt(np.linalg.det(2 * math.pi * pr.S))
    total = 0.0
    marg = np.zeros((len(priors), M + 1))  # last column: missed
    for theta in itertools.product(range(-1, M), repeat=len(priors)):
        assigned = [i for i in theta if i >= 0]
        if len(set(assigned)) != len(assigned):
            continue
        if any(i >= 0 and not gated[t, i] for t, i in enumerate(theta)):
            continue
        w = lam ** (M - len(assigned))
        for t, i in enumerate(theta):
            w *= pds[t] * lik[t, i] if i >= 0 else 1.0 - pds[t] * pg
        total += w
        for t, i in enumerate(theta):
            marg[t, i if i >= 0 else M] += w
    return marg / total, gated


def _scenario(rng: np.random.Generator, n_tracks: int, n_returns: int):
    priors = [
        _prior(*rng.uniform(0.0, 120.0, 2), sigma=rng.uniform(10.0, 40.0)) for _ in range(n_tracks)
    ]
    Z = rng.uniform(-20.0, 140.0, (n_returns, 2))
    return priors, Z


@pytest.mark.parametrize("seed", range(60))
def test_marginals_equal_the_brute_force_enumeration(seed: int) -> None:
    rng = np.random.default_rng(seed)
    priors, Z = _scenario(rng, int(rng.integers(1, 5)), int(rng.integers(0, 6)))
    lam = float(rng.choice([1e-5, 1e-4, 1e-3]))
    pds = rng.uniform(0.3, 0.99, len(priors)).tolist()
    pg = 0.99
    res = jpda_update(priors, Z, POS, lam, pd=pds, gate_probability=pg)
    assert res.exact
    marg, gated = _brute_force(priors, Z, POS, lam, pds, pg)
    for t, u in enumerate(res.updates):
        np.testing.assert_array_equal(u.gated, np.flatnonzero(gated[t]))
        np.testing.assert_allclose(u.beta, marg[t, u.gated], rtol=1e-10, atol=1e-13)
        assert u.beta0 == pytest.approx(marg[t, -1], rel=1e-10, abs=1e-13)
        assert u.beta0 + u.beta.sum() == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("seed", range(20))
def test_zero_clutter_and_certain_detection_are_the_limits(seed: int) -> None:
    """λ = 0 (or P_D P_G = 1) is the ε → 0 limit: the brute force at a tiny λ (or P_D = 1 − δ)
    approaches the exact answer."""
    rng = np.random.default_rng(1000 + seed)
    priors, Z = _scenario(rng, int(rng.integers(2, 4)), int(rng.integers(1, 5)))
    res = jpda_update(priors, Z, POS, 0.0, pd=0.8, gate_probability=0.99)
    marg, _ = _brute_force(priors, Z, POS, 1e-30, [0.8] * len(priors), 0.99)
    for t, u in enumerate(res.updates):
        np.testing.assert_allclose(u.beta, marg[t, u.gated], atol=1e-9)
        assert u.beta0 == pytest.approx(marg[t, -1], abs=1e-9)
    res = jpda_update(priors, Z, POS, 1e-4, pd=1.0, gate_probability=1.0)
    marg, _ = _brute_force(priors, Z, POS, 1e-4, [1.0 - 2.0**-52] * len(priors), 1.0)
    for t, u in enumerate(res.updates):  # the brute force's error is O(δ / λ g)
        np.testing.assert_allclose(u.beta, marg[t, u.gated], atol=1e-7)
        assert u.beta0 == pytest.approx(marg[t, -1], abs=1e-7)


def test_far_apart_tracks_are_two_pdas_bit_for_bit() -> None:
    rng = np.random.default_rng(5)
    model = RangeBearingModel(
        sensor_xy=(0.0, 0.0), sigma_r=20.0, sigma_bearing=2e-3, pd=0.9, clutter_rate=2.0
    )
    priors = [_prior(10_000.0, 2_000.0, 60.0), _prior(-3_000.0, 8_000.0, 60.0)]
    Z = []
    for p in priors:
        z0 = model.h(p.x)
        Z.append(z0 + rng.normal(0.0, [20.0, 2e-3]))
        Z.append(z0 + rng.normal(0.0, [60.0, 6e-3]))
    Zs = np.array(Z)
    for lam in (0.0, 1e-4):
        res = jpda_update(priors, Zs, model, lam)
        assert [c.method for c in res.clusters] == ["pda", "pda"]
        for p, u in zip(priors, res.updates, strict=True):
            ref = pda_update(p, Zs, model, lam)
            np.testing.assert_array_equal(u.posterior.x, ref.posterior.x)
            np.testing.assert_array_equal(u.posterior.P, ref.posterior.P)
            np.testing.assert_array_equal(u.beta, ref.beta)
            assert u.beta0 == ref.beta0
            np.testing.assert_array_equal(u.gated, ref.gated)


def test_one_track_equals_pda_update_including_empty_and_undetectable() -> None:
    p = _prior(50.0, 50.0)
    Z = np.array([[55.0, 48.0], [900.0, 900.0]])
    for pd in (0.0, 0.5, 1.0):
        for ZZ in (Z, np.zeros((0, 2))):
            u = jpda_update([p], ZZ, POS, 1e-3, pd=pd).updates[0]
            ref = pda_update(p, ZZ, POS, 1e-3, pd=pd)
            np.testing.assert_array_equal(u.posterior.x, ref.posterior.x)
            np.testing.assert_array_equal(u.posterior.P, ref.posterior.P)
            assert u.beta0 == ref.beta0


def test_shared_return_splits_between_two_tracks_symmetrically() -> None:
    """Two identical tracks and one return exactly between them: equal marginals."""
    a, b = _prior(0.0, 0.0), _prior(20.0, 0.0)
    res = jpda_update([a, b], np.array([[10.0, 0.0]]), POS, 1e-4, pd=0.9)
    assert len(res.clusters) == 1 and res.clusters[0].method == "exact"
    assert res.clusters[0].n_events == 3  # none, a<-z, b<-z
    ua, ub = res.updates
    assert ua.beta[0] == pytest.approx(ub.beta[0], rel=1e-12)
    assert ua.beta[0] < 0.5  # the return is one track's at most


def test_chained_gates_make_one_cluster() -> None:
    priors = [_prior(0.0, 0.0), _prior(60.0, 0.0), _prior(120.0, 0.0), _prior(5000.0, 0.0)]
    Z = np.array([[30.0, 0.0], [90.0, 0.0], [5000.0, 1.0]])
    preds = [predict_measurement(p, POS) for p in priors]
    gates = [track_gate(pr, Z, 0.9, 0.99) for pr in preds]
    cl = clusters_of(gates)
    assert [c[0].tolist() for c in cl] == [[0, 1, 2], [3]]
    assert [c[1].tolist() for c in cl] == [[0, 1], [2]]
    res = jpda_update(priors, Z, POS, 1e-4)
    np.testing.assert_array_equal(res.ungated_rows(3), np.zeros(0, dtype=np.intp))
    res = jpda_update(priors[3:], Z, POS, 1e-4)
    np.testing.assert_array_equal(res.ungated_rows(3), [0, 1])


@pytest.mark.parametrize("seed", range(15))
def test_gnn_fallback_picks_the_most_probable_joint_event(seed: int) -> None:
    rng = np.random.default_rng(200 + seed)
    priors, Z = _scenario(rng, 3, 4)
    lam = 1e-4
    pds = [0.85] * 3
    res = jpda_update(priors, Z, POS, lam, pd=pds, max_events=1)
    marg, gated = _brute_force(priors, Z, POS, lam, pds, 0.99)
    # the most probable joint event, by brute force
    best, best_w = None, -1.0
    M = Z.shape[0]
    preds = [predict_measurement(p, POS) for p in priors]
    for theta in itertools.product(range(-1, M), repeat=3):
        used = [i for i in theta if i >= 0]
        if len(set(used)) != len(used) or any(
            i >= 0 and not gated[t, i] for t, i in enumerate(theta)
        ):
            continue
        w = lam ** (M - len(used))
        for t, i in enumerate(theta):
            if i < 0:
                w *= 1.0 - 0.85 * 0.99
            else:
                pr = preds[t]
                nu = Z[i] - pr.zhat
                d2 = nu @ np.linalg.solve(pr.S, nu)
                w *= 0.85 * math.exp(-0.5 * d2) / math.sqrt(np.linalg.det(2 * math.pi * pr.S))
        if w > best_w:
            best, best_w = theta, w
    assert best is not None
    for c in res.clusters:
        assert c.method == ("pda" if c.tracks.size == 1 else "gnn")
    for t, u in enumerate(res.updates):
        cluster = next(c for c in res.clusters if t in c.tracks.tolist())
        if cluster.method == "pda":
            continue
        if best[t] < 0:
            assert u.beta0 == 1.0 and not u.beta.any()
        else:
            assert u.beta0 == 0.0
            assert u.gated[np.flatnonzero(u.beta == 1.0)].tolist() == [best[t]]
    assert res.exact == all(c.tracks.size == 1 for c in res.clusters)


def test_event_cap_counts_events() -> None:
    """n tracks all gating the same k returns: Σ_j C(n,j) C(k,j) j! feasible events."""
    priors = [_prior(float(i), 0.0, 200.0) for i in range(4)]
    Z = np.array([[0.0, 0.0], [5.0, 0.0], [0.0, 5.0]])
    res = jpda_update(priors, Z, POS, 1e-4)
    n, k = 4, 3
    count = sum(math.comb(n, j) * math.comb(k, j) * math.factorial(j) for j in range(4))
    assert res.clusters[0].n_events == count
    res_cap = jpda_update(priors, Z, POS, 1e-4, max_events=count - 1)
    assert res_cap.clusters[0].method == "gnn" and not res_cap.exact
    assert jpda_update(priors, Z, POS, 1e-4, max_events=count).exact


def test_bad_inputs_are_named() -> None:
    with pytest.raises(ValueError, match="clutter_density"):
        jpda_update([_prior(0, 0)], np.zeros((0, 2)), POS, -1.0)
    with pytest.raises(ValueError, match="pd"):
        jpda_update([_prior(0, 0)], np.zeros((0, 2)), POS, 0.0, pd=[0.5, 0.5])
    with pytest.raises(ValueError, match="max_events"):
        jpda_update([_prior(0, 0)], np.zeros((0, 2)), POS, 0.0, max_events=0)


def test_gate_reused_from_association() -> None:
    p = _prior(0.0, 0.0)
    Z = np.array([[1.0, 2.0], [400.0, 0.0]])
    pr = predict_measurement(p, POS)
    rows, _, _ = gate(pr, Z, 0.99)
    np.testing.assert_array_equal(jpda_update([p], Z, POS, 1e-3).updates[0].gated, rows)
