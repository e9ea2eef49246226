"""Fusion rules of the decentralized mode (covnet.core.fusion): information-matrix fusion equals
the centralized filter; covariance intersection is optimal, order independent, batched == one at
a time; bad input is refused with a clear message."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.optimize import minimize, minimize_scalar

from covnet.core.fusion import (
    CI_OBJECTIVES,
    LocalTrack,
    ci_candidates,
    ci_weights,
    covariance_intersection,
    information_fusion,
)
from covnet.core.gaussian import Gaussian
from covnet.core.kalman import predict, update, update_information, update_sequential
from covnet.core.motion import cv_transition, dwna_process_noise
from covnet.core.sensing import correlated_noise, position_matrix


def rand_spd(rng: np.random.Generator, d: int, cond: float = 1e3) -> np.ndarray:
    """A random SPD matrix with eigenvalues spread log-uniformly over ``cond``."""
    Q, _ = np.linalg.qr(rng.standard_normal((d, d)))
    lam = np.exp(rng.uniform(0.0, np.log(cond), d))
    return (Q * lam) @ Q.T


def all_masks(ns: int) -> np.ndarray:
    codes = np.arange(1, 2**ns)
    return ((codes[:, None] >> np.arange(ns)) & 1).astype(bool)


def objective_value(w: np.ndarray, Y: np.ndarray, objective: str) -> float:
    """``log det P(w)`` (det) or ``tr P(w)`` (trace), ``P(w) = inv(Σ w_i Y_i)``."""
    P = np.linalg.inv(np.tensordot(w, Y, axes=1))
    return float(np.linalg.slogdet(P)[1] if objective == "det" else np.trace(P))


def scipy_reference(Y: np.ndarray, objective: str) -> float:
    """The optimum by scipy: minimize_scalar for two components, SLSQP on the simplex (several
    starts, tight tolerance) otherwise."""
    n = Y.shape[0]
    if n == 1:
        return objective_value(np.ones(1), Y, objective)
    if n == 2:
        res = minimize_scalar(
            lambda t: objective_value(np.array([t, 1.0 - t]), Y, objective),
            bounds=(0.0, 1.0),
            method="bounded",
            options={"xatol": 1e-13},
        )
        ends = [objective_value(np.array(e), Y, objective) for e in ((1.0, 0.0), (0.0, 1.0))]
        return min([float(res.fun), *ends])
    best = np.inf
    for start in [np.full(n, 1.0 / n), *(0.7 * np.eye(n)[i] + 0.3 / n for i in range(n))]:
        res = minimize(
            objective_value,
            start,
            args=(Y, objective),
            method="SLSQP",
            bounds=[(0.0, 1.0)] * n,
            constraints=[{"type": "eq", "fun": lambda w: w.sum() - 1.0}],
            options={"ftol": 1e-15, "maxiter": 500},
        )
        w = np.clip(res.x, 0.0, None)
        # evaluated on the simplex: SLSQP's own value may profit from sum(w) = 1 + 1e-13
        best = min(best, objective_value(w / w.sum(), Y, objective))
    return best


# --------------------------------------------------------------------------------------------
# covariance intersection: basic identities
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("objective", CI_OBJECTIVES)
def test_ci_of_identical_tracks_is_that_track(objective):
    rng = np.random.default_rng(1)
    a = Gaussian(rng.standard_normal(4), rand_spd(rng, 4))
    for k in (2, 3):
        fused = covariance_intersection([a] * k, objective)
        np.testing.assert_allclose(fused.P, a.P, rtol=1e-12, atol=1e-12 * np.abs(a.P).max())
        np.testing.assert_allclose(fused.x, a.x, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("objective", CI_OBJECTIVES)
def test_ci_of_one_track_is_that_track(objective):
    rng = np.random.default_rng(2)
    a = Gaussian(rng.standard_normal(3), rand_spd(rng, 3))
    fused = covariance_intersection([a], objective)
    np.testing.assert_allclose(fused.P, a.P, rtol=1e-12, atol=1e-12 * np.abs(a.P).max())
    np.testing.assert_allclose(fused.x, a.x, rtol=1e-12, atol=1e-12)
    w = ci_weights(np.linalg.inv(a.P)[None, None], np.ones((1, 1), dtype=bool), objective)
    assert w.tolist() == [[1.0]]


@pytest.mark.parametrize("objective", CI_OBJECTIVES)
def test_weights_on_the_simplex_and_zero_off_the_mask(objective):
    rng = np.random.default_rng(3)
    M, n, d = 30, 5, 3
    Y = np.array([[np.linalg.inv(rand_spd(rng, d)) for _ in range(n)] for _ in range(M)])
    mask = rng.random((M, n)) < 0.5
    mask[np.arange(M), rng.integers(0, n, M)] = True
    Y_garbage = np.where(mask[..., None, None], Y, -7.0)  # masked-out entries are ignored
    w = ci_weights(Y_garbage, mask, objective)
    assert w.shape == (M, n)
    assert np.all(w >= 0.0)
    assert np.all(w[~mask] == 0.0)
    np.testing.assert_allclose(w.sum(axis=1), 1.0, rtol=0, atol=1e-14)
    assert np.array_equal(w, ci_weights(Y, mask, objective))


def test_fast_weights_closed_form():
    rng = np.random.default_rng(4)
    P = np.array([rand_spd(rng, 4) for _ in range(3)])
    w = ci_weights(np.linalg.inv(P)[None], np.ones((1, 3), dtype=bool), "fast")[0]
    inv_tr = 1.0 / np.trace(P, axis1=1, axis2=2)
    np.testing.assert_allclose(w, inv_tr / inv_tr.sum(), rtol=1e-12)


@pytest.mark.parametrize("objective", CI_OBJECTIVES)
def test_duplicated_track_changes_nothing(objective):
    """Identical components (a singular KKT system without the damping): CI(a, a, b) has the
    covariance of CI(a, b) for the optimising rules."""
    rng = np.random.default_rng(13)
    for _ in range(5):
        a, b = (Gaussian(rng.standard_normal(4), rand_spd(rng, 4)) for _ in range(2))
        two = covariance_intersection([a, b], objective).P
        three = covariance_intersection([a, b, a], objective).P
        if objective == "fast":  # closed form: a's weight grows, so only check it is valid
            assert np.all(np.linalg.eigvalsh(three) > 0)
            continue
        np.testing.assert_allclose(three, two, rtol=1e-10, atol=1e-10 * np.abs(two).max())


@pytest.mark.parametrize("objective", ["det", "trace"])
def test_order_independence(objective):
    rng = np.random.default_rng(5)
    for _ in range(5):
        tracks = [Gaussian(rng.standard_normal(4), rand_spd(rng, 4)) for _ in range(4)]
        Y = np.linalg.inv(np.stack([t.P for t in tracks]))
        ref = covariance_intersection(tracks, objective)
        w_ref = ci_weights(Y[None], np.ones((1, 4), dtype=bool), objective)[0]
        for perm in itertools.permutations(range(4)):
            p = list(perm)
            fused = covariance_intersection([tracks[i] for i in p], objective)
            scale = np.abs(ref.P).max()
            np.testing.assert_allclose(fused.P, ref.P, rtol=1e-10, atol=1e-10 * scale)
            np.testing.assert_allclose(fused.x, ref.x, rtol=1e-9, atol=1e-9)
            w = ci_weights(Y[p][None], np.ones((1, 4), dtype=bool), objective)[0]
            np.testing.assert_allclose(w, w_ref[p], rtol=0, atol=1e-8)


def test_deterministic_bits():
    rng = np.random.default_rng(6)
    P_prior = rand_spd(rng, 4)
    P_local = np.array([rand_spd(rng, 4) for _ in range(6)])
    masks = all_masks(6)
    for objective in CI_OBJECTIVES:
        a = ci_candidates(P_prior, P_local, masks, objective)
        b = ci_candidates(P_prior.copy(), P_local.copy(), masks.copy(), objective)
        assert np.array_equal(a, b)


# --------------------------------------------------------------------------------------------
# covariance intersection: optimality against scipy
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("objective", ["det", "trace"])
def test_weights_optimal_against_scipy(objective):
    """Mixed mask sizes (1..5 components) in one batch, d = 2..4: our objective is never worse
    than scipy's optimum and within 1e-8 relative of it."""
    rng = np.random.default_rng(7 if objective == "det" else 8)
    M, n = 36, 5
    for d in (2, 4):
        Y = np.array([[np.linalg.inv(rand_spd(rng, d)) for _ in range(n)] for _ in range(M)])
        mask = np.zeros((M, n), dtype=bool)
        for i in range(M):
            mask[i, rng.permutation(n)[: 1 + i % n]] = True
        w = ci_weights(Y, mask, objective)
        for i in range(M):
            ours = objective_value(w[i][mask[i]], Y[i][mask[i]], objective)
            ref = scipy_reference(Y[i][mask[i]], objective)
            scale = 1.0 if objective == "det" else abs(ref)  # det: log det, so relative in det P
            assert ours <= ref + 1e-12 * scale, (i, ours, ref)
            assert abs(ours - ref) <= 1e-8 * scale, (i, ours, ref)


@pytest.mark.parametrize("objective", ["det", "trace"])
def test_weights_satisfy_kkt_with_many_components(objective):
    """Many components (6 and 12, d = 2 and 4, ill-conditioned): some reach 0 on the way and
    must re-enter (the KKT check of the active set).  Certificate of optimality of the convex
    problem: ``g_i = μ`` on the support and ``g_i >= μ`` off it (``μ = Σ w_i g_i``)."""
    rng = np.random.default_rng(12)
    for d, n in itertools.product((2, 4), (6, 12)):
        Y = np.array([[np.linalg.inv(rand_spd(rng, d, 1e4)) for _ in range(n)] for _ in range(150)])
        w = ci_weights(Y, np.ones(Y.shape[:2], dtype=bool), objective)
        P = np.linalg.inv(np.einsum("mi,miab->mab", w, Y))
        if objective == "det":
            g = -np.einsum("mab,miba->mi", P, Y)
        else:
            g = -np.einsum("mab,mibc,mca->mi", P, Y, P)
        mu = (w * g).sum(axis=1, keepdims=True)
        tol = 1e-8 * np.abs(mu)
        assert np.all(np.where(w > 1e-6, np.abs(g - mu), 0.0) <= tol)
        assert np.all(np.where(w == 0.0, g - mu, 0.0) >= -tol)


# --------------------------------------------------------------------------------------------
# covariance intersection: batched candidates == one at a time
# --------------------------------------------------------------------------------------------


def _subset_tracks(P_prior, P_local, row):
    zero = np.zeros(P_prior.shape[0])
    return [Gaussian(zero, P_prior)] + [Gaussian(zero, P_local[j]) for j in np.flatnonzero(row)]


@pytest.mark.parametrize("objective", CI_OBJECTIVES)
def test_candidates_equal_one_at_a_time(objective):
    rng = np.random.default_rng(9)
    P_prior = rand_spd(rng, 4, cond=1e4)
    P_local = np.array([rand_spd(rng, 4, cond=1e4) for _ in range(6)])
    masks = all_masks(6)
    out = ci_candidates(P_prior, P_local, masks, objective)
    assert out.shape == (masks.shape[0], 4, 4)
    for i, row in enumerate(masks):
        P = covariance_intersection(_subset_tracks(P_prior, P_local, row), objective).P
        np.testing.assert_allclose(out[i], P, rtol=1e-12, atol=1e-12 * np.abs(P).max())
    # an empty row: the prior alone
    empty = ci_candidates(P_prior, P_local, np.zeros((1, 6), dtype=bool), objective)[0]
    np.testing.assert_allclose(empty, P_prior, rtol=1e-12, atol=1e-12 * np.abs(P_prior).max())


def test_candidates_paper_like_problem():
    """The bench's problem (paper sensors, a few local scans): candidates == one at a time, and
    a candidate is never larger (det) than the prior alone."""
    from covnet.covariance_control.bench_fusion import paper_problem

    P_prior, P_local = paper_problem(8)
    masks = all_masks(8)
    out = ci_candidates(P_prior, P_local, masks, "det")
    for i in range(0, masks.shape[0], 17):
        P = covariance_intersection(_subset_tracks(P_prior, P_local, masks[i]), "det").P
        np.testing.assert_allclose(out[i], P, rtol=1e-12, atol=1e-12 * np.abs(P).max())
    assert np.all(np.linalg.slogdet(out)[1] <= np.linalg.slogdet(P_prior)[1] + 1e-12)


# --------------------------------------------------------------------------------------------
# information-matrix fusion == centralized filter
# --------------------------------------------------------------------------------------------


def _sensors():
    """(H, R) of four sensors with different measurement models."""
    pos = position_matrix()
    x_vx = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]])
    y_only = np.array([[0.0, 0.0, 1.0, 0.0]])
    return [
        (pos, correlated_noise(21.1, 8.2, 0.82)),
        (pos, correlated_noise(8.22, 20.3, 0.78)),
        (x_vx, correlated_noise(15.0, 3.0, 0.3)),
        (y_only, np.array([[30.0**2]])),
    ]


@pytest.mark.parametrize("all_tracks", [False, True])
def test_information_fusion_equals_centralized(all_tracks):
    """Per-sensor local filters over 8 scans with different enable patterns; the fused prior is
    the previous fused posterior predicted.  Fusion == the centralized sequential Joseph update
    == the information-form update, to 1e-9 relative, at every scan."""
    rng = np.random.default_rng(10)
    F, Q = cv_transition(1.0), dwna_process_noise(1.0, 0.5)
    sensors = _sensors()
    P0 = np.diag([1e4, 1e2, 1e4, 1e2])
    truth = np.array([0.0, 426.0, 0.0, 0.0])
    x0 = truth + rng.multivariate_normal(np.zeros(4), P0)
    central = fused = Gaussian(x0, P0)
    local = [Gaussian(x0 + rng.standard_normal(4), P0 * (1 + j)) for j in range(len(sensors))]
    patterns = [
        [True, True, True, True],
        [True, False, False, False],
        [False, False, False, False],
        [False, True, True, False],
        [True, True, False, True],
        [False, False, True, True],
        [True, False, True, False],
        [True, True, True, True],
    ]
    for enabled in patterns:
        truth = F @ truth + rng.multivariate_normal(np.zeros(4), Q)
        meas, tracks = [], []
        for j, ((H, R), on) in enumerate(zip(sensors, enabled, strict=True)):
            prior_j = predict(local[j], F, Q)
            if on:
                z = H @ truth + rng.multivariate_normal(np.zeros(H.shape[0]), R)
                meas.append((z, H, R))
                local[j] = update(prior_j, z, H, R)
            else:
                local[j] = prior_j
            if on or all_tracks:
                tracks.append(LocalTrack(post=local[j], prior=prior_j))
        fused_prior = predict(fused, F, Q)
        fused = information_fusion(fused_prior, tracks)
        central = update_sequential(predict(central, F, Q), meas)
        info = update_information(fused_prior, meas)
        for ref in (central, info):
            np.testing.assert_allclose(fused.P, ref.P, rtol=1e-9, atol=1e-9 * np.abs(ref.P).max())
            np.testing.assert_allclose(fused.x, ref.x, rtol=1e-9, atol=1e-9 * np.abs(ref.x).max())
        assert np.array_equal(fused.P, fused.P.T)


def test_information_fusion_without_tracks_is_the_prior():
    rng = np.random.default_rng(11)
    prior = Gaussian(rng.standard_normal(4), rand_spd(rng, 4))
    fused = information_fusion(prior, [])
    np.testing.assert_allclose(fused.P, prior.P, rtol=1e-12, atol=1e-12 * np.abs(prior.P).max())
    np.testing.assert_allclose(fused.x, prior.x, rtol=1e-10, atol=1e-12)


# --------------------------------------------------------------------------------------------
# bad input
# --------------------------------------------------------------------------------------------


def test_ci_weights_bad_input():
    Y = np.broadcast_to(np.eye(2), (2, 3, 2, 2)).copy()
    ok = np.ones((2, 3), dtype=bool)
    with pytest.raises(ValueError, match=r"Y must be \(M, n, d, d\).*got shape \(3, 2, 2\)"):
        ci_weights(Y[0], ok[0])
    with pytest.raises(ValueError, match=r"Y must be \(M, n, d, d\).*got shape \(2, 3, 2, 3\)"):
        ci_weights(np.zeros((2, 3, 2, 3)), ok)
    with pytest.raises(ValueError, match=r"mask must be \(M, n\) like Y = \(2, 3\), got shape"):
        ci_weights(Y, np.ones((2, 2), dtype=bool))
    with pytest.raises(ValueError, match="mask must be a boolean array.*dtype int64"):
        ci_weights(Y, np.ones((2, 3), dtype=np.int64))
    empty = ok.copy()
    empty[1] = False
    with pytest.raises(ValueError, match="mask row 1 has no component"):
        ci_weights(Y, empty)
    with pytest.raises(ValueError, match=r"objective must be one of \('det', 'trace', 'fast'\)"):
        ci_weights(Y, ok, "logdet")
    bad = Y.copy()
    bad[1, 2] = -np.eye(2)
    with pytest.raises(ValueError, match=r"Y\[1, 2\] must be a symmetric positive definite"):
        ci_weights(bad, ok)
    bad[1, 2] = [[1.0, 0.5], [0.0, 1.0]]
    with pytest.raises(ValueError, match=r"Y\[1, 2\] must be a symmetric positive definite"):
        ci_weights(bad, ok)
    bad[1, 2, 0, 0] = np.nan
    with pytest.raises(ValueError, match="Y has non-finite entries"):
        ci_weights(bad, ok)


def test_covariance_intersection_bad_input():
    a = Gaussian(np.zeros(2), np.eye(2))
    with pytest.raises(ValueError, match="tracks is empty"):
        covariance_intersection([])
    with pytest.raises(ValueError, match=r"tracks\[1\] has dimension 3, tracks\[0\] 2"):
        covariance_intersection([a, Gaussian(np.zeros(3), np.eye(3))])
    with pytest.raises(ValueError, match=r"tracks P\[1\] must be a symmetric positive definite"):
        covariance_intersection([a, Gaussian(np.zeros(2), -np.eye(2))])
    with pytest.raises(ValueError, match="objective must be one of"):
        covariance_intersection([a], "max")


def test_ci_candidates_bad_input():
    P, PL, masks = np.eye(3), np.stack([np.eye(3)] * 4), all_masks(4)
    with pytest.raises(ValueError, match=r"P_prior must be a square \(d, d\).*got shape \(3, 2\)"):
        ci_candidates(np.ones((3, 2)), PL, masks)
    with pytest.raises(ValueError, match=r"P_local must be \(Ns, 3, 3\).*got shape \(4, 2, 2\)"):
        ci_candidates(P, PL[:, :2, :2], masks)
    with pytest.raises(
        ValueError, match=r"masks must be \(M, Ns\) = \(M, 4\).*got shape \(15, 3\)"
    ):
        ci_candidates(P, PL, masks[:, :3])
    with pytest.raises(ValueError, match=r"masks must be \(M, Ns\) = \(M, 4\).*got shape \(4,\)"):
        ci_candidates(P, PL, masks[0])
    with pytest.raises(ValueError, match="masks must be a boolean array"):
        ci_candidates(P, PL, masks.astype(int))
    with pytest.raises(ValueError, match="P_prior must be a finite symmetric positive definite"):
        ci_candidates(-P, PL, masks)
    bad = PL.copy()
    bad[2] = np.diag([1.0, 0.0, 1.0])
    with pytest.raises(ValueError, match=r"P_local\[2\] must be a symmetric positive definite"):
        ci_candidates(P, bad, masks)
    with pytest.raises(ValueError, match="objective must be one of"):
        ci_candidates(P, PL, masks, "Det")


def test_information_fusion_bad_input():
    prior = Gaussian(np.zeros(2), np.eye(2))
    t3 = LocalTrack(Gaussian(np.zeros(3), np.eye(3)), Gaussian(np.zeros(3), np.eye(3)))
    with pytest.raises(ValueError, match=r"tracks\[0\] has dimension 3, the prior 2"):
        information_fusion(prior, [t3])
    with pytest.raises(ValueError, match="LocalTrack.post and .prior must have the same dimension"):
        LocalTrack(Gaussian(np.zeros(2), np.eye(2)), Gaussian(np.zeros(3), np.eye(3)))
    with pytest.raises(ValueError, match=r"prior.P must be symmetric positive definite"):
        information_fusion(Gaussian(np.zeros(2), -np.eye(2)), [])
    # a "posterior" with less information than its prior: the fused Y is not positive definite
    loose = LocalTrack(
        Gaussian(np.zeros(2), 10 * np.eye(2)), Gaussian(np.zeros(2), 0.01 * np.eye(2))
    )
    with pytest.raises(ValueError, match="fused information Y is not positive definite"):
        information_fusion(prior, [loose])


def test_ci_that_takes_one_track_whole_keeps_its_mean_exactly():
    """A local track from a sensor with R's least eigenvalue 2e-16 m² (σ 1e-6 m, ρ 0.9999),
    beside a looser prediction: the weights are [0, 1], so CI is that track.  Its mean went
    through inv(P) and back: 30 m/s (120 standard deviations) off in velocity, and a ci run
    diverged (NEES 1 000) where central and info did not."""
    F, Q = cv_transition(1.0), dwna_process_noise(1.0, 0.5)
    H = position_matrix()
    R = correlated_noise(1e-6, 1e-6, 0.9999)
    rng = np.random.default_rng(0)
    truth = np.array([0.0, 426.0, 0.0, 0.0])
    P0 = np.diag([1e4, 1e2, 1e4, 1e2])
    g = Gaussian(truth + rng.normal(size=4) * np.sqrt(np.diag(P0)), P0)
    for _ in range(2):
        truth = F @ truth
        g = update(predict(g, F, Q), H @ truth + np.linalg.cholesky(R) @ rng.normal(size=2), H, R)
    prior = Gaussian(np.array([800.0, 400.0, 0.0, 0.0]), np.diag([500.0, 100.0, 500.0, 100.0]))
    fused = covariance_intersection([prior, g], "det")
    np.testing.assert_array_equal(fused.x, g.x)
    e = fused.x - g.x
    assert e @ np.linalg.solve(fused.P, e) == 0.0
