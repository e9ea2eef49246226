"""Properties of the fusion rules: covariance intersection is consistent for any admissible
cross-correlation, its weights satisfy the KKT conditions, the batched candidates equal one CI at
a time; information-matrix fusion of exact local tracks equals the information-form update."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

# the SPD strategy of the allocation properties (A Aᵀ + floor I, entries in [-10, 10])
from test_allocation_equivalence import _elems, spd

from covnet.core import fusion
from covnet.core.gaussian import Gaussian
from covnet.core.kalman import update, update_information


@st.composite
def joint_problem(draw):
    """``n`` component estimates of a ``d``-state with a joint error covariance ``S (nd, nd)``
    (random, possibly of low rank plus a small ridge: strongly correlated errors included);
    the components' covariances are its diagonal blocks."""
    n = draw(st.integers(2, 3))
    d = draw(st.integers(1, 4))
    r = draw(st.integers(1, n * d))
    A = draw(arrays(np.float64, (n * d, r), elements=_elems))
    ridge = draw(st.sampled_from([1e-3, 1e-1, 1.0]))
    S = A @ A.T + ridge * np.eye(n * d)
    return n, d, S


@given(joint_problem(), st.sampled_from(fusion.CI_OBJECTIVES))
def test_ci_consistent_for_any_cross_correlation(pb, objective):
    """``x̂ = Σ K_i x̂_i`` with ``K_i = P w_i P_i⁻¹`` (unbiased: ``Σ K_i = I``) has the exact error
    covariance ``K S Kᵀ``; CI's ``P`` must dominate it: ``λ_min(P − K S Kᵀ) >= −1e-9 scale``."""
    n, d, S = pb
    blocks = [S[i * d : (i + 1) * d, i * d : (i + 1) * d] for i in range(n)]
    tracks = [Gaussian(np.zeros(d), B) for B in blocks]
    P = fusion.covariance_intersection(tracks, objective).P
    Y = np.linalg.inv(np.stack(blocks))
    w = fusion.ci_weights(Y[None], np.ones((1, n), dtype=bool), objective)[0]
    K = np.concatenate([P @ (w[i] * Y[i]) for i in range(n)], axis=1)
    np.testing.assert_allclose(K @ np.kron(np.ones((n, 1)), np.eye(d)), np.eye(d), atol=1e-6)
    err = K @ S @ K.T
    scale = max(np.abs(P).max(), np.abs(err).max())
    assert np.linalg.eigvalsh(P - 0.5 * (err + err.T)).min() >= -1e-9 * scale


@st.composite
def ci_batch(draw):
    M = draw(st.integers(1, 6))
    n = draw(st.integers(1, 5))
    d = draw(st.integers(1, 4))
    Y = np.array([[np.linalg.inv(draw(spd(d, floor=0.1))) for _ in range(n)] for _ in range(M)])
    mask = draw(arrays(np.bool_, (M, n)))
    mask[:, 0] |= ~mask.any(axis=1)
    return Y, mask


@given(ci_batch(), st.sampled_from(["det", "trace"]))
def test_ci_weights_satisfy_kkt(pb, objective):
    """First-order optimality on the simplex: with ``g_i = −tr(P Y_i)`` (det) or
    ``−tr(P Y_i P)`` (trace) and ``μ = Σ w_i g_i``, every positive weight has ``g_i = μ`` and
    every component at 0 has ``g_i >= μ`` (to 1e-7 relative)."""
    Y, mask = pb
    w = fusion.ci_weights(Y, mask, objective)
    assert np.all(w >= 0) and np.all(w[~mask] == 0)
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-14)
    for m in range(Y.shape[0]):
        P = np.linalg.inv(np.tensordot(w[m], Y[m], axes=1))
        if objective == "det":
            g = -np.einsum("ab,iba->i", P, Y[m])
        else:
            g = -np.einsum("ab,ibc,ca->i", P, Y[m], P)
        mu = float(w[m] @ g)
        tol = 1e-7 * abs(mu)
        on = mask[m] & (w[m] > 1e-6)
        assert np.all(np.abs(g[on] - mu) <= tol), (g, mu, w[m])
        assert np.all(g[mask[m] & (w[m] == 0)] >= mu - tol), (g, mu, w[m])


@given(st.integers(1, 4), st.integers(1, 4), st.data(), st.sampled_from(fusion.CI_OBJECTIVES))
def test_candidates_equal_one_at_a_time(ns, d, data, objective):
    P_prior = data.draw(spd(d, floor=0.1))
    P_local = np.stack([data.draw(spd(d, floor=0.1)) for _ in range(ns)])
    codes = np.arange(1, 2**ns)
    masks = ((codes[:, None] >> np.arange(ns)) & 1).astype(bool)
    out = fusion.ci_candidates(P_prior, P_local, masks, objective)
    zero = np.zeros(d)
    for i, row in enumerate(masks):
        tracks = [Gaussian(zero, P_prior)] + [
            Gaussian(zero, P_local[j]) for j in np.flatnonzero(row)
        ]
        P = fusion.covariance_intersection(tracks, objective).P
        np.testing.assert_allclose(out[i], P, rtol=1e-12, atol=1e-12 * np.abs(P).max())


@st.composite
def fusion_problem(draw):
    n = draw(st.integers(1, 4))
    prior = Gaussian(draw(arrays(np.float64, (n,), elements=_elems)), draw(spd(n, floor=1.0)))
    tracks, meas = [], []
    for _ in range(draw(st.integers(0, 3))):
        local_prior = Gaussian(
            draw(arrays(np.float64, (n,), elements=_elems)), draw(spd(n, floor=1.0))
        )
        m = draw(st.integers(1, n))
        H = draw(arrays(np.float64, (m, n), elements=_elems))
        R = draw(spd(m, floor=1.0))
        z = draw(arrays(np.float64, (m,), elements=_elems))
        tracks.append(fusion.LocalTrack(post=update(local_prior, z, H, R), prior=local_prior))
        meas.append((z, H, R))
    return prior, tracks, meas


@given(fusion_problem())
def test_information_fusion_equals_information_update(pb):
    """Each local filter's bracket is its sensor's measurement information, whatever its own
    prior: fusion == the information-form update of the fused prior with those measurements."""
    prior, tracks, meas = pb
    fused = fusion.information_fusion(prior, tracks)
    ref = update_information(prior, meas)
    scale = np.abs(ref.P).max()
    np.testing.assert_allclose(fused.P, ref.P, rtol=1e-6, atol=1e-6 * scale)
    x_scale = np.abs(ref.x).max() + np.sqrt(np.abs(np.diag(ref.P)).max())
    np.testing.assert_allclose(fused.x, ref.x, rtol=1e-6, atol=1e-6 * x_scale)
