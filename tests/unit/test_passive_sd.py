"""S-D costs (spec §8.2), triangulation, greedy, the MILP and LR on passive scenes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from covnet.core.passive.exact import associate_milp, solve_milp
from covnet.core.passive.lagrangian import associate_lr, solve_lr
from covnet.core.passive.model import AssocParams, angles
from covnet.core.passive.sd import greedy, sd_costs, triangulate
from covnet.passive.scene import PAPER_SENSORS, SceneModel, draw, formation, score

S = np.asarray(PAPER_SENSORS)


def _model(form="cross", d=1.0, sigma=1e-3, clutter=False) -> SceneModel:
    return SceneModel(
        S,
        formation(form, d),
        np.full(3, sigma),
        np.full(3, sigma),
        0.95 if clutter else 1.0,
        0.25 if clutter else 0.0,
    )


def test_triangulation_is_exact_without_noise_for_triples_and_pairs():
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(2, 8, 20), rng.uniform(2, 8, 20), rng.uniform(0.5, 2, 20)])
    ang = angles(S, pts)  # (20, 3, 2)
    det = np.ones((20, 3), dtype=bool)
    det[10:, 1] = False  # pairs (s1, s3)
    sig = np.full(3, 1e-3)
    tri = triangulate(S, ang[..., 0], ang[..., 1], det, sig, sig)
    assert tri.ok.all()
    np.testing.assert_allclose(tri.x, pts, atol=1e-9)
    assert np.all(tri.chi2 < 1e-12)


def test_gauss_newton_keeps_the_best_iterate():
    rng = np.random.default_rng(1)
    p = np.array([5.0, 5.0, 1.0])
    ang = angles(S, p)[None] + rng.normal(0, 5e-3, size=(200, 3, 2))
    det = np.ones((200, 3), dtype=bool)
    sig = np.full(3, 5e-3)
    start = triangulate(S, ang[..., 0], ang[..., 1], det, sig, sig, steps=0)
    gn = triangulate(S, ang[..., 0], ang[..., 1], det, sig, sig, steps=3)
    assert np.all(gn.chi2 <= start.chi2 + 1e-12)
    assert np.mean(gn.chi2) < np.mean(start.chi2)
    # the ML chi2 of a correct triple is ~ chi2 with 6 - 3 = 3 degrees of freedom
    assert np.mean(gn.chi2) == pytest.approx(3.0, rel=0.2)


def test_clean_costs_allow_complete_triples_only():
    scene = draw(_model(), 3, 0)
    costs = sd_costs(scene.scan, scene_params := _model().params())
    C = costs.C
    assert costs.complete_only and scene_params.complete_only
    assert np.isfinite(C[1:, 1:, 1:]).all()
    mask = np.ones(C.shape, dtype=bool)
    mask[1:, 1:, 1:] = False
    mask[0, 0, 0] = False
    assert np.isinf(C[mask]).all()
    assert costs.n_tuples == 125


def test_clutter_costs_singletons_gating_and_the_target_prior_term():
    model = _model(clutter=True)
    scene = draw(model, 5, 1)
    with_tau = sd_costs(scene.scan, model.params(target_density=0.025))
    without = sd_costs(scene.scan, model.params(target_density=0.0))
    for costs in (with_tau, without):
        C = costs.C
        assert (C[1:, 0, 0] == 0).all() and (C[0, 1:, 0] == 0).all() and (C[0, 0, 1:] == 0).all()
        fin = np.isfinite(C)
        fin[0, 0, 0] = False
        assert np.all(C[fin] <= 0)  # C > 0 is gated
    # where both are finite they differ by tau = -ln lb - 3/2 ln 2pi + 1/2 ln det(J'R^-1 J)
    both = np.isfinite(with_tau.C) & np.isfinite(without.C)
    idx = np.argwhere(both)
    idx = idx[(idx > 0).sum(axis=1) >= 2]
    assert len(idx) > 0
    zs = scene.scan.z
    for t in idx[:10]:
        det = t > 0
        az = np.array([zs[s][t[s] - 1, 0] if det[s] else 0.0 for s in range(3)])
        el = np.array([zs[s][t[s] - 1, 1] if det[s] else 0.0 for s in range(3)])
        sig = model.sigma_azimuth
        tri = triangulate(S, az[None], el[None], det[None], sig, sig)
        tau = -math.log(0.025) - 1.5 * math.log(2 * math.pi) + 0.5 * tri.logdet[0]
        assert with_tau.C[tuple(t)] - without.C[tuple(t)] == pytest.approx(tau, abs=1e-9)


def test_kappa_and_mu_of_a_pair():
    """A noise-free pair costs 2 κ + μ + τ with χ² = 0."""
    model = _model(clutter=True)
    p = model.params(target_density=0.0)
    t = formation("cross", 1.0)[1]
    ang = angles(S, t)
    from covnet.core.passive.model import PassiveScan

    scan = PassiveScan(S, (ang[0:1], ang[1:2], np.zeros((0, 2))))
    C = sd_costs(scan, p).C
    kappa = math.log(p.clutter_density * 2 * math.pi * 1e-6 / 0.95)
    mu = -math.log(0.05)
    assert C[1, 1, 0] == pytest.approx(2 * kappa + mu, abs=1e-9)


def test_lr_matches_milp_on_passive_scenes_and_bounds_hold():
    reached = 0
    n = 0
    for clutter in (False, True):
        model = _model(d=0.5, sigma=3e-3, clutter=clutter)
        params = model.params()
        for trial in range(12):
            scene = draw(model, 8, trial)
            costs = sd_costs(scene.scan, params)
            ex = solve_milp(costs)
            lr = solve_lr(costs)
            assert ex.status == 0
            tol = 1e-7 * max(1.0, abs(ex.cost))
            assert lr.lower <= ex.cost + tol <= lr.upper + 2 * tol
            reached += lr.upper <= ex.cost + tol
            n += 1
    assert reached >= 0.9 * n


def test_greedy_is_beaten_by_the_exact_ghosts_of_the_cross_formation():
    model = _model(form="cross", d=1.0, sigma=1e-3)
    params = model.params()
    hits = {"greedy": 0, "milp": 0, "lr": 0}
    truth = 0
    for trial in range(20):
        scene = draw(model, 4, trial)
        truth += len(scene.truth)
        for name, f in (("greedy", greedy), ("milp", associate_milp), ("lr", associate_lr)):
            a = f(scene.scan, params)
            hits[name] += score(scene.truth, a.triples)[0]
            Z = a.tuples
            for s in range(3):
                real = Z[:, s][Z[:, s] >= 0]
                assert len(set(real.tolist())) == len(real)
    assert hits["milp"] == truth and hits["lr"] == truth
    assert hits["greedy"] < 0.92 * truth


def test_params_validation():
    with pytest.raises(ValueError, match="sigma_azimuth"):
        AssocParams.isotropic(0.0)
    with pytest.raises(ValueError, match="clutter_density"):
        AssocParams.isotropic(1e-3, p_detect=0.9)
    with pytest.raises(ValueError, match="p_detect"):
        AssocParams.isotropic(1e-3, p_detect=1.5)
