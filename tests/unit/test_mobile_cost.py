"""The batched cost tensor equals a plain per-candidate Kalman update and Pd (spec §8.3 item 1)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.linalg import sqrtm

from covnet.core.gaussian import Gaussian
from covnet.core.kalman import update
from covnet.core.mobile.cost import CostParams, cost_tensor, inverse_scale
from covnet.core.mobile.models import C_POS, MODES, Sensors


def _instance(seed: int, M: int = 4, N: int = 3, correlated: bool = False):
    rng = np.random.default_rng(seed)
    x = np.column_stack(
        [
            rng.uniform(0, 300, M),
            rng.uniform(-2, 2, M),
            rng.uniform(0, 300, M),
            rng.uniform(-2, 2, M),
        ]
    )
    A = rng.normal(size=(M, 4, 4))
    P = A @ np.swapaxes(A, 1, 2) + np.diag([20.0, 0.2, 20.0, 0.2])
    R0 = rng.uniform(2, 3, N)[:, None, None] ** 2 * np.eye(2)
    if correlated:
        R0[:, 0, 1] = R0[:, 1, 0] = 0.4 * np.sqrt(R0[:, 0, 0] * R0[:, 1, 1])
    sensors = Sensors(
        position=rng.uniform(0, 300, (N, 2)),
        speed=rng.uniform(2, 3, N),
        R0=R0,
        r_pd=rng.uniform(40, 80, N),
        b0=rng.uniform(0.8, 1.2, N),
        b1=rng.uniform(0.0, 0.3, N),
        capacity=np.full(N, np.inf),
    )
    return x, P, sensors


def _reference(x, P, s: Sensors, p: CostParams):
    """One candidate at a time: R from (I + D L⁻¹)-style growth through sqrtm, a Joseph-form
    Kalman update (covnet.core.kalman.update), Pd from the bell, ω from np.std."""
    M, N = x.shape[0], s.count
    md, tr, b = np.empty((M, N, 9)), np.empty((M, N, 9)), np.empty((N, 9))
    for i, j, r in itertools.product(range(M), range(N), range(9)):
        qd = s.speed[j] * MODES[r]
        q = s.position[j] + p.T * qd
        if p.dist_uses_velocity:
            D = np.array([np.hypot(x[i, 0] - q[0], x[i, 1] - qd[0]),
                          np.hypot(x[i, 2] - q[1], x[i, 3] - qd[1])])  # fmt: skip
        else:
            D = np.abs([x[i, 0] - q[0], x[i, 2] - q[1]])
        G = np.eye(2) + np.diag(D / np.asarray(p.L))
        Gh = np.real(sqrtm(G))
        R = Gh @ s.R0[j] @ Gh
        post = update(Gaussian(x[i], P[i]), C_POS @ x[i], C_POS, R)
        tr[i, j, r] = (
            np.trace(post.P) if p.trace_kind == "full" else np.trace(C_POS @ post.P @ C_POS.T)
        )
        S = s.r_pd[j] ** 2 * np.eye(2)
        if p.pd_include_track_cov:
            S = S + C_POS @ P[i] @ C_POS.T
        e = C_POS @ x[i] - q
        d = np.sqrt(e @ np.linalg.solve(S, e))
        md[i, j, r] = 1.0 - p.PD / (1.0 + abs((d - p.c) / p.a) ** (2 * p.b))
        b[j, r] = s.b0[j] + s.b1[j] * np.linalg.norm(MODES[r])
    w = [1.0 / np.std(md), 1.0 / np.std(tr), 1.0 / np.std(np.broadcast_to(b, (M, N, 9)))]
    c = p.gamma * w[0] * md + p.alpha * w[1] * tr + p.beta * w[2] * b[None]
    tr0 = [np.trace(Pi) if p.trace_kind == "full" else Pi[0, 0] + Pi[2, 2] for Pi in P]
    pen = 1000.0 + 10.0 * np.abs(c).max() if p.null_penalty is None else p.null_penalty
    c0 = p.gamma * w[0] + p.alpha * w[1] * np.array(tr0) + pen
    return md, tr, b, c, c0


FLAGS = [
    ("default", CostParams(), False),
    ("position-trace", CostParams(trace_kind="position"), False),
    ("no-velocity-in-D", CostParams(dist_uses_velocity=False), False),
    ("pd-track-cov", CostParams(pd_include_track_cov=True), False),
    ("correlated-R0", CostParams(), True),
    ("ring-T2-L", CostParams(T=2.0, c=0.5, a=0.7, b=1.5, L=(20.0, 40.0), null_penalty=0.0), True),
]


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("params,correlated", [f[1:] for f in FLAGS], ids=[f[0] for f in FLAGS])
def test_cost_tensor_equals_per_candidate_update(params, correlated, seed):
    x, P, sensors = _instance(seed, correlated=correlated)
    ct = cost_tensor(x, P, sensors, params)
    md, tr, b, c, c0 = _reference(x, P, sensors, params)
    assert ct.c.shape == (4, 3, 9)
    np.testing.assert_allclose(ct.md, md, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(ct.tr, tr, rtol=1e-12)
    np.testing.assert_allclose(ct.b, b, rtol=1e-14)
    np.testing.assert_allclose(ct.c, c, rtol=1e-11)
    np.testing.assert_allclose(ct.c0, c0, rtol=1e-11)


def test_inverse_scale_falls_back_to_the_mean_when_constant():
    assert inverse_scale(np.array([1.0, 3.0])) == pytest.approx(1.0)
    assert inverse_scale(np.full(5, 0.8)) == pytest.approx(1.0 / 0.8)
    assert inverse_scale(np.zeros(4)) == 1.0
    assert inverse_scale(np.array([])) == 1.0


def test_equal_usage_costs_use_the_mean_and_the_null_option_is_dearer():
    x, P, sensors = _instance(5)
    from dataclasses import replace

    s = replace(sensors, b0=np.ones(3), b1=np.zeros(3))
    ct = cost_tensor(x, P, s, CostParams())
    assert ct.omega[2] == pytest.approx(1.0)
    assert np.all(ct.c0 > ct.c.max(axis=(1, 2)) + 1000.0)
    assert ct.penalty == pytest.approx(1000.0 + 10.0 * np.abs(ct.c).max())


def test_no_sensors_or_no_targets():
    x, P, sensors = _instance(1)
    none = sensors.subset(np.array([], dtype=np.intp))
    ct = cost_tensor(x, P, none, CostParams())
    assert ct.c.shape == (4, 0, 9) and ct.c0.shape == (4,)
    ct = cost_tensor(x[:0], P[:0], sensors, CostParams())
    assert ct.c.shape == (0, 3, 9)
