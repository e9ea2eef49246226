"""The cot method's closed forms (spec §4-§6) and the §11 checklist items 1-4 in the paper
layout: noise-free identities, the Monte Carlo variance check, the exact ghosts of the cross
formation, the indicator analysis."""

from __future__ import annotations

import numpy as np
import pytest

from covnet.core.passive.cotangent import (
    HEIGHT_PAIRS,
    associate_cot,
    azimuth_candidates,
    azimuth_statistic,
    height_statistic,
    indicator_analysis,
)
from covnet.core.passive.model import AssocParams, PassiveScan, angles
from covnet.passive.scene import PAPER_SENSORS, formation

S = np.asarray(PAPER_SENSORS)
SIG = np.full(3, 1e-3)


def _triple_angles(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Angles of ``points[s]`` seen from sensor ``s`` (one point per sensor): az, el ``(3,)``."""
    ang = np.array([angles(S[s : s + 1], points[s])[0] for s in range(3)])
    return ang[:, 0], ang[:, 1]


def _noise_free_scan(points: np.ndarray) -> PassiveScan:
    ang = angles(S, points)  # (N, 3, 2)
    return PassiveScan(S, (ang[:, 0], ang[:, 1], ang[:, 2]))


# ------------------------------------------------------------------ §4 azimuth statistic


def test_paper_layout_closed_form():
    """In the paper layout F = 10 [k1 (1 + k2 − k3) − k3]."""
    rng = np.random.default_rng(1)
    a = rng.uniform(0.2, 2.9, size=(3, 50)) * rng.choice([-1, 1], size=(3, 50))
    F, _ = azimuth_statistic(S, a[0], a[1], a[2], SIG)
    k1, k2, k3 = 1 / np.tan(a)
    np.testing.assert_allclose(F, 10 * (k1 * (1 + k2 - k3) - k3), rtol=1e-12, atol=1e-9)


def test_F_is_the_determinant_of_the_lines_divided_by_the_sines():
    rng = np.random.default_rng(2)
    sensors = rng.uniform(-10, 10, size=(3, 3))
    a = rng.uniform(-3, 3, size=(3, 40))
    F, _ = azimuth_statistic(sensors, a[0], a[1], a[2], SIG)
    D, _ = azimuth_statistic(sensors, a[0], a[1], a[2], SIG, form="sine")
    for n in range(40):
        M = np.array(
            [
                [
                    np.sin(a[i, n]),
                    -np.cos(a[i, n]),
                    -np.sin(a[i, n]) * sensors[i, 0] + np.cos(a[i, n]) * sensors[i, 1],
                ]
                for i in range(3)
            ]
        )
        # rows (sin, −cos, −sin x + cos y) = L_i; F = det / Π sin with columns 2, 3 negated
        assert np.linalg.det(M) == pytest.approx(D[n], rel=1e-9, abs=1e-9)
        assert D[n] == pytest.approx(F[n] * np.prod(np.sin(a[:, n])), rel=1e-9, abs=1e-9)


def test_F_geometric_meaning():
    """F = (k1 − k2) δ, δ the x offset between P12 = L1 ∩ L2 and L3 at the same y."""
    rng = np.random.default_rng(3)
    for _ in range(20):
        a = rng.uniform(0.3, 2.8, size=3) * rng.choice([-1, 1], size=3)
        F, _ = azimuth_statistic(S, *a, SIG)
        k = 1 / np.tan(a)
        # L_i: x = x_i + k_i (y − y_i)
        y = (S[1, 0] - S[0, 0] - k[1] * S[1, 1] + k[0] * S[0, 1]) / (k[0] - k[1])
        x12 = S[0, 0] + k[0] * (y - S[0, 1])
        x3 = S[2, 0] + k[2] * (y - S[2, 1])
        assert F == pytest.approx((k[0] - k[1]) * (x12 - x3), rel=1e-9, abs=1e-9)


@pytest.mark.parametrize("form", ["cot", "sine"])
def test_first_order_variance_against_finite_differences(form):
    rng = np.random.default_rng(4)
    sig = np.array([1e-3, 2e-3, 3e-3])
    for _ in range(10):
        a = rng.uniform(0.3, 2.8, size=3) * rng.choice([-1, 1], size=3)
        _, s = azimuth_statistic(S, *a, sig, form=form)
        h = 1e-6
        grad = []
        for i in range(3):
            e = np.zeros(3)
            e[i] = h
            fp, _ = azimuth_statistic(S, *(a + e), sig, form=form)
            fm, _ = azimuth_statistic(S, *(a - e), sig, form=form)
            grad.append((fp - fm) / (2 * h))
        assert s == pytest.approx(np.sqrt(np.sum((sig * np.array(grad)) ** 2)), rel=1e-6)


@pytest.mark.parametrize("name", ["horizontal", "cross"])
@pytest.mark.parametrize("d", [0.5, 1.0, 2.0])
def test_noise_free_true_triples_are_exact(name, d):
    targets = formation(name, d)
    for t in targets:
        az, el = _triple_angles(np.array([t, t, t]))
        F, sF = azimuth_statistic(S, *az, SIG)
        assert abs(F) <= 1e-9 * max(sF, 1e-12) or abs(F) < 1e-13
        e, se, ok = height_statistic(S, az[None], el[None], SIG, SIG)
        assert ok.all()
        assert np.all(np.abs(e) < 1e-9 * se)


def test_central_target_degeneracy():
    """T1 (5,5) lies on s1-s2: F ≡ 0 for (T1@s1, T1@s2, any k3) and ∂F/∂k3 = 0."""
    t1 = np.array([5.0, 5.0, 1.0])
    az, _ = _triple_angles(np.array([t1, t1, t1]))
    for a3 in np.linspace(-3.0, 3.0, 13):
        if abs(np.sin(a3)) < 1e-3:
            continue
        F, _ = azimuth_statistic(S, az[0], az[1], a3, SIG)
        assert abs(F) < 1e-12
        Fp, _ = azimuth_statistic(S, az[0], az[1], a3 + 1e-4, SIG)
        assert abs(Fp) < 1e-12


def test_noise_free_horizontal_azimuth_test_passes_true_plus_four_degenerate():
    """Spec §4: without noise exactly the 4 false triples (T1, T1, other) pass the azimuth
    test in the horizontal formation; the elevation test removes them."""
    targets = formation("horizontal", 1.0)
    scan = _noise_free_scan(targets)
    params = AssocParams.isotropic(1e-3)
    Q, _, _ = azimuth_candidates(scan, params)
    got = {tuple(q) for q in Q.tolist()}
    true = {(i, i, i) for i in range(5)}
    assert true <= got
    assert got - true == {(0, 0, k) for k in range(1, 5)}
    a = associate_cot(scan, params)
    assert {tuple(t) for t in a.triples.tolist()} == true
    assert a.info["n_azimuth"] == 9 and a.info["n_elevation"] == 5


# ------------------------------------------------------------------ exact ghosts (§10)


@pytest.mark.parametrize("d", [0.5, 1.0, 2.0])
def test_cross_formation_exact_ghosts(d):
    T = formation("cross", d)
    ghosts = {  # (target at s1, at s2, at s3) -> ghost point
        (4, 2, 0): np.array([50, 50, 10]) / (10 + d),
        (3, 1, 0): np.array([50, 50, 10]) / (10 - d),
    }
    for (i1, i2, i3), g in ghosts.items():
        # the ghost point is seen in exactly the directions of those targets
        for s, ti in enumerate((i1, i2, i3)):
            np.testing.assert_allclose(
                angles(S[s : s + 1], g)[0], angles(S[s : s + 1], T[ti])[0], atol=1e-12
            )
        az, el = _triple_angles(np.array([T[i1], T[i2], T[i3]]))
        F, sF = azimuth_statistic(S, *az, SIG)
        assert abs(F) < 1e-9 * sF
        e, se, ok = height_statistic(S, az[None], el[None], SIG, SIG)
        assert ok.all() and np.all(np.abs(e) < 1e-9 * se)
    # ... and the indicator analysis' forced rows reject them on a clean scan
    scan = _noise_free_scan(T)
    a = associate_cot(scan, AssocParams.isotropic(1e-3))
    assert {tuple(t) for t in a.triples.tolist()} == {(i, i, i) for i in range(5)}


# ------------------------------------------------------------------ §5 heights


def _heights_reference(sensors, az, el):
    """Straight from the spec, one candidate, no vectorisation: h1..h4."""

    def pair(i, j):
        D = np.sin(az[j] - az[i])
        dx, dy = sensors[j, 0] - sensors[i, 0], sensors[j, 1] - sensors[i, 1]
        ri = (dx * np.sin(az[j]) - dy * np.cos(az[j])) / D
        rj = (dx * np.sin(az[i]) - dy * np.cos(az[i])) / D
        return ri, rj

    r1, r3a = pair(0, 2)
    r2, r3b = pair(1, 2)
    z = sensors[:, 2]
    return np.array(
        [
            z[0] + r1 * np.tan(el[0]),
            z[2] + r3a * np.tan(el[2]),
            z[1] + r2 * np.tan(el[1]),
            z[2] + r3b * np.tan(el[2]),
        ]
    )


def test_heights_match_reference_and_finite_difference_variance():
    rng = np.random.default_rng(5)
    sensors = np.array([[0.0, 10.0, 0.3], [10.0, 0.0, -0.2], [0.0, 0.0, 0.1]])
    sig_a, sig_e = np.array([1e-3, 2e-3, 1.5e-3]), np.array([2e-3, 1e-3, 3e-3])
    sigma = np.concatenate([sig_a, sig_e])
    for _ in range(10):
        p = np.array([rng.uniform(2, 8), rng.uniform(2, 8), rng.uniform(0.5, 3)])
        ang = angles(sensors, p) + rng.normal(0, 0.01, size=(3, 2))
        az, el = ang[:, 0], ang[:, 1]
        e, se, ok = height_statistic(sensors, az[None], el[None], sig_a, sig_e)
        h = _heights_reference(sensors, az, el)
        np.testing.assert_allclose(
            e[0], [h[a] - h[b] for a, b in HEIGHT_PAIRS], rtol=1e-10, atol=1e-12
        )
        theta = np.concatenate([az, el])
        eps = 1e-7
        J = np.empty((4, 6))
        for n in range(6):
            tp, tm = theta.copy(), theta.copy()
            tp[n] += eps
            tm[n] -= eps
            J[:, n] = (
                _heights_reference(sensors, tp[:3], tp[3:])
                - _heights_reference(sensors, tm[:3], tm[3:])
            ) / (2 * eps)
        want = [np.sqrt(np.sum((sigma * (J[a] - J[b])) ** 2)) for a, b in HEIGHT_PAIRS]
        np.testing.assert_allclose(se[0], want, rtol=1e-5)


def test_parallel_projected_lines_are_rejected_without_warnings():
    az = np.array([[0.3, 1.0, 0.3]])  # α1 = α3: D13 = 0
    el = np.full((1, 3), 0.1)
    _, _, ok = height_statistic(S, az, el, SIG, SIG)
    assert not ok[0]


def test_lines_of_sight_along_x_need_the_sine_form():
    """A LOS parallel to the x axis has k = ±inf: the cot form rejects it (no warning), the
    sine form still tests it."""
    sensors = np.array([[0.0, 5.0, 0.0], [10.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    target = np.array([5.0, 5.0, 1.0])  # seen from sensor 1 at azimuth exactly 0
    ang = angles(sensors, target[None])[0]
    scan = PassiveScan(sensors, (ang[0:1], ang[1:2], ang[2:3]))
    assert ang[0, 0] == 0.0
    cot = associate_cot(scan, AssocParams.isotropic(1e-3, azimuth_form="cot"))
    sine = associate_cot(scan, AssocParams.isotropic(1e-3, azimuth_form="sine"))
    assert cot.triples.shape[0] == 0
    assert sine.triples.tolist() == [[0, 0, 0]]


# ------------------------------------------------------------------ §11.2 Monte Carlo


@pytest.mark.parametrize("sigma", [1e-3, 3e-3])
def test_monte_carlo_variance_and_rejection_rates(sigma):
    """1e5 draws around T2 of the cross formation: var/σ² within 1 ± 0.02 for F and every
    e_ab; true-triple rejection ≈ 0.27 % (azimuth) and ≈ 1.1 % (elevation)."""
    rng = np.random.default_rng(20260611)
    n = 100_000
    t = formation("cross", 1.0)[1]
    az0, el0 = _triple_angles(np.array([t, t, t]))
    az = az0 + sigma * rng.standard_normal((n, 3))
    el = el0 + sigma * rng.standard_normal((n, 3))
    sig = np.full(3, sigma)
    _, sF0 = azimuth_statistic(S, *az0, sig)
    F, sF = azimuth_statistic(S, az[:, 0], az[:, 1], az[:, 2], sig)
    assert np.var(F) / sF0**2 == pytest.approx(1.0, abs=0.02)
    rej_az = np.mean(np.abs(F) > 3 * sF)
    assert 0.0018 < rej_az < 0.0037
    _, se0, _ = height_statistic(S, az0[None], el0[None], sig, sig)
    e, se, ok = height_statistic(S, az, el, sig, sig)
    assert ok.all()
    np.testing.assert_allclose(np.var(e, axis=0) / se0[0] ** 2, 1.0, atol=0.02)
    rej_el = np.mean(np.any(np.abs(e) > 3 * se, axis=1))
    assert 0.008 < rej_el < 0.014
    rej = np.mean((np.abs(F) > 3 * sF) | np.any(np.abs(e) > 3 * se, axis=1))
    assert 0.010 < rej < 0.017


# ------------------------------------------------------------------ §6 indicator analysis


def test_indicator_analysis_forced_rows_first():
    """Row 0 is the cheapest but shares each of its measurements with another row, so it is not
    forced; rows 1-3 each hold a measurement nobody else claims (ξ = 1).  The analysis accepts
    the forced rows, cheapest first, and row 0 (a ghost-like row) dies; plain cheapest-first
    would have taken row 0 and lost the other three."""
    P = np.array([[0, 0, 0], [0, 1, 1], [1, 0, 2], [2, 2, 0]])
    psi = np.array([0.1, 0.5, 0.3, 0.4])
    rows = indicator_analysis(P, psi)
    assert rows.tolist() == [2, 3, 1]


def test_indicator_analysis_case_two_and_disjointness():
    # every measurement appears twice: no forced row, the cheapest live row goes first
    P = np.array([[0, 0, 0], [0, 1, 1], [1, 1, 0], [1, 0, 1]])
    psi = np.array([0.4, 0.2, 0.3, 0.9])
    rows = indicator_analysis(P, psi)
    assert rows[0] == 1
    Z = P[rows]
    for col in range(3):
        assert len(set(Z[:, col].tolist())) == len(Z)
    assert indicator_analysis(np.zeros((0, 3), dtype=int), np.zeros(0)).shape == (0,)


def test_empty_sensor_list_gives_empty_association():
    e = np.zeros((0, 2))
    scan = PassiveScan(S, (np.array([[0.5, 0.1]]), e, np.array([[0.7, 0.1]])))
    a = associate_cot(scan, AssocParams.isotropic(1e-3))
    assert a.triples.shape == (0, 3) and a.status == 0


def test_no_candidate_survives_the_azimuth_test():
    # three lines of sight that meet nowhere near each other
    z = (np.array([[-0.1, 0.1]]), np.array([[2.0, 0.1]]), np.array([[0.2, 0.1]]))
    a = associate_cot(PassiveScan(S, z), AssocParams.isotropic(1e-3))
    assert a.triples.shape == (0, 3)
    assert a.info == {"n_triples": 1, "n_azimuth": 0, "n_elevation": 0}


@pytest.mark.parametrize("form", ["cot", "sine"])
def test_normalised_cost_and_sine_form_solve_a_noisy_scene(form):
    from covnet.passive.scene import SceneModel, draw

    model = SceneModel(S, formation("horizontal", 2.0), np.full(3, 1e-3), np.full(3, 1e-3))
    hits = 0
    for trial in range(10):
        sc = draw(model, 3, trial)
        a = associate_cot(sc.scan, model.params(cot_cost="normalised", azimuth_form=form))
        hits += len({tuple(t) for t in a.triples.tolist()} & {tuple(t) for t in sc.truth.tolist()})
    assert hits >= 46  # of 50; ~1.4 % of true triples fail a 3-sigma test
