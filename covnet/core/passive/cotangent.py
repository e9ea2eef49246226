"""The fast passive association of Tian, Ji and Ouyang: two closed-form tests on the cotangents
of the measured angles, then the indicator-function analysis (spec §4-§7).

Pipeline (:func:`associate_cot`), with no triangulation, matrix inversion or iteration:

1. per measurement: ``cos α, sin α, k = cot α`` and ``tan ε``, once;
2. azimuth test on all ``n1 n2 n3`` triples (broadcast) -> candidate set Q;
3. elevation (height) test on Q -> candidate set P with cost Ψ;
4. indicator analysis on P -> the associated triples Z.

Indices are 0-based: sensor ``i`` here is sensor ``i + 1`` of the spec, and sensor 2 (spec's
S3) is the reference shared by the height pairs (1,3) and (2,3).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import NDArray

from covnet.core.gaussian import Mat, Vec
from covnet.core.passive.model import Association, AssocParams, Index, PassiveScan

__all__ = [
    "HEIGHT_PAIRS",
    "PARALLEL_EPS",
    "associate_cot",
    "azimuth_candidates",
    "azimuth_statistic",
    "elevation_candidates",
    "height_statistic",
    "indicator_analysis",
]

F64 = NDArray[np.float64]

#: ``|D_ij| = |sin(α_j − α_i)|`` below this: parallel projected LOS, the candidate is rejected.
PARALLEL_EPS = 1e-9
#: the six height differences ``e_ab = h_a − h_b``, ``a < b`` (0-based ``a, b``)
HEIGHT_PAIRS: tuple[tuple[int, int], ...] = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))


# --------------------------------------------------------------------------------------------
# §4 azimuth test
# --------------------------------------------------------------------------------------------


def azimuth_statistic(
    sensors: Mat,
    a1: F64,
    a2: F64,
    a3: F64,
    sigma_azimuth: Vec,
    form: Literal["cot", "sine"] = "cot",
) -> tuple[F64, F64]:
    """Concurrency statistic of the three projected LOS and its first-order std; broadcasts
    ``a1, a2, a3`` (azimuths in rad of sensors 1, 2, 3).

    ``form="cot"`` (the paper's), with ``k_i = cot α_i``::

        F = k1 (x2 − x3) + k2 (x3 − x1) + k3 (x1 − x2)
            + k1 k2 (y1 − y2) + k2 k3 (y2 − y3) + k3 k1 (y3 − y1)        [km]
        σ_F² = Σ_i σ_{α,i}² (1 + k_i²)² (∂F/∂k_i)²
        ∂F/∂k1 = (x2 − x3) + k2 (y1 − y2) + k3 (y3 − y1)   (and cyclically, spec §4)

    ``form="sine"``: the sine-weighted determinant ``D = F Π sin α_i = det[sin α_i, cos α_i,
    x_i sin α_i − y_i cos α_i]`` with ``σ_D² = Σ_i σ_{α,i}² (∂D/∂α_i)²``; the same zero set, and
    finite when a LOS is parallel to the x axis (where ``k`` is infinite and the cot form gives
    non-finite values, which the tests reject).

    Both are exactly 0 for a noise-free correct triple; σ is evaluated at the measured angles.
    """
    x, y = sensors[:, 0], sensors[:, 1]
    s2 = np.asarray(sigma_azimuth, dtype=np.float64) ** 2
    if form == "sine":
        c1, c2, c3 = np.cos(a1), np.cos(a2), np.cos(a3)
        n1, n2, n3 = np.sin(a1), np.sin(a2), np.sin(a3)
        rows = [
            (n, c, x[i] * n - y[i] * c) for i, (n, c) in enumerate(((n1, c1), (n2, c2), (n3, c3)))
        ]
        drows = [
            (c, -n, x[i] * c + y[i] * n) for i, (n, c) in enumerate(((n1, c1), (n2, c2), (n3, c3)))
        ]
        D = _det3(*rows)
        dD = (
            _det3(drows[0], rows[1], rows[2]),
            _det3(rows[0], drows[1], rows[2]),
            _det3(rows[0], rows[1], drows[2]),
        )
        var = s2[0] * dD[0] ** 2 + s2[1] * dD[1] ** 2 + s2[2] * dD[2] ** 2
        return D, np.sqrt(var)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        k1, k2, k3 = (np.cos(a) / np.sin(a) for a in (a1, a2, a3))
        F, var = _cot_stat(x, y, k1, k2, k3, s2)
        return F, np.sqrt(var)


def _cot_stat(x: F64, y: F64, k1: F64, k2: F64, k3: F64, s2: F64) -> tuple[F64, F64]:
    """``F`` and ``σ_F²`` from cotangents (see :func:`azimuth_statistic`); grouped as
    ``F = k1 ∂F/∂k1 + k2 (x3 − x1) + k3 (x1 − x2 + k2 (y2 − y3))`` to share work with the
    derivatives."""
    x12, x23, x31 = x[0] - x[1], x[1] - x[2], x[2] - x[0]
    y12, y23, y31 = y[0] - y[1], y[1] - y[2], y[2] - y[0]
    k2y23 = k2 * y23
    d1 = (x23 + k2 * y12) + k3 * y31
    d2 = (x31 + k1 * y12) + k3 * y23
    d3 = (x12 + k2y23) + k1 * y31
    F = k1 * d1 + k2 * x31 + k3 * (x12 + k2y23)
    w1 = s2[0] * (1.0 + k1 * k1) ** 2
    w2 = s2[1] * (1.0 + k2 * k2) ** 2
    w3 = s2[2] * (1.0 + k3 * k3) ** 2
    return F, w1 * d1 * d1 + w2 * d2 * d2 + w3 * d3 * d3


def _det3(r1: tuple[F64, ...], r2: tuple[F64, ...], r3: tuple[F64, ...]) -> F64:
    """``det [r1; r2; r3]`` by cofactors, broadcasting the entries."""
    a1, b1, c1 = r1
    a2, b2, c2 = r2
    a3, b3, c3 = r3
    return a1 * (b2 * c3 - b3 * c2) - b1 * (a2 * c3 - a3 * c2) + c1 * (a2 * b3 - a3 * b2)


def azimuth_candidates(scan: PassiveScan, params: AssocParams) -> tuple[Index, F64, F64]:
    """The azimuth test on all ``n1 n2 n3`` triples: keep ``|F| ≤ gate · σ_F``.

    Returns the kept triples ``Q`` ``(q, 3)`` (row-major order of ``(i1, i2, i3)``) and their
    ``F``, ``σ_F``.  Non-finite statistics are rejected.
    """
    a = [zi[:, 0] for zi in scan.z]
    F, sF = azimuth_statistic(
        scan.sensors,
        a[0][:, None, None],
        a[1][None, :, None],
        a[2][None, None, :],
        params.sigma_azimuth,
        params.azimuth_form,
    )
    with np.errstate(invalid="ignore"):
        keep = np.abs(F) <= params.gate * sF
    Q = np.argwhere(keep)
    return Q, F[keep], sF[keep]


# --------------------------------------------------------------------------------------------
# §5 elevation (height) test
# --------------------------------------------------------------------------------------------


def _heights(sensors: Mat, c: F64, n: F64, t: F64) -> tuple[F64, F64, NDArray[np.bool_]]:
    """The four heights ``h`` ``(4, m)`` and their gradients ``G`` ``(4, 6, m)`` with respect to
    ``θ = (α1, α2, α3, ε1, ε2, ε3)``, from per-candidate ``cos α``, ``sin α``, ``tan ε``
    ``(m, 3)``; ``valid`` ``(m,)``: both pairs testable (``|D| ≥ PARALLEL_EPS``).

    Pairs ``(i, j) ∈ {(1, 3), (2, 3)}`` (computed together): ``D = sin(α_j − α_i)``,
    ``Δ = s_j − s_i``, signed ranges ``r_i = (Δx sin α_j − Δy cos α_j)/D``,
    ``r_j = (Δx sin α_i − Δy cos α_i)/D``, and
    ``∂r_i/∂α_i = r_i cot(α_j − α_i)``, ``∂r_i/∂α_j = −r_j/D``, ``∂r_j/∂α_i = r_i/D``,
    ``∂r_j/∂α_j = −r_j cot(α_j − α_i)``.  Heights ``h_m(ij) = z_m + r_m(ij) tan ε_m``:
    ``h1 = h_1(13)``, ``h2 = h_3(13)``, ``h3 = h_2(23)``, ``h4 = h_3(23)``, with
    ``∂h_m/∂α = tan ε_m ∂r_m/∂α`` and ``∂h_m/∂ε_m = r_m (1 + tan² ε_m)``.
    """
    m = c.shape[0]
    si, sj = sensors[:2], sensors[2]
    dx = (sj[0] - si[:, 0])[:, None]
    dy = (sj[1] - si[:, 1])[:, None]
    ci, ni, ti = c[:, :2].T, n[:, :2].T, t[:, :2].T  # (2, m): sensors 1 and 2
    cj, nj, tj = c[:, 2], n[:, 2], t[:, 2]  # (m,): the reference sensor 3
    D = nj * ci - cj * ni
    ok = np.abs(D) >= PARALLEL_EPS
    inv = 1.0 / np.where(ok, D, 1.0)
    ri = (dx * nj - dy * cj) * inv
    rj = (dx * ni - dy * ci) * inv
    cot = (cj * ci + nj * ni) * inv
    h = np.stack([sensors[:2, 2, None] + ri * ti, sj[2] + rj * tj], axis=1).reshape(4, m)
    G = np.zeros((2, 2, 6, m))  # (pair, i/j, θ, candidate)
    G[_P2, 0, _P2] = ti * ri * cot  # ∂h_i/∂α_i
    G[:, 0, 2] = -ti * rj * inv  # ∂h_i/∂α_3
    G[_P2, 0, _P2 + 3] = ri * (1.0 + ti * ti)  # ∂h_i/∂ε_i
    G[_P2, 1, _P2] = tj * ri * inv  # ∂h_3/∂α_i
    G[:, 1, 2] = -tj * rj * cot  # ∂h_3/∂α_3
    G[:, 1, 5] = rj * (1.0 + tj * tj)  # ∂h_3/∂ε_3
    return h, G.reshape(4, 6, m), np.logical_and.reduce(ok, axis=0)


_P2 = np.array([0, 1])
_PA = np.array([a for a, _ in HEIGHT_PAIRS])
_PB = np.array([b for _, b in HEIGHT_PAIRS])


def _height_diffs(
    sensors: Mat, c: F64, n: F64, t: F64, sigma: Vec
) -> tuple[F64, F64, NDArray[np.bool_]]:
    """``e`` ``(6, m)``, ``σ(e)`` ``(6, m)`` and ``valid`` ``(m,)``."""
    h, G, valid = _heights(sensors, c, n, t)
    e = h[_PA] - h[_PB]
    dG = G[_PA] - G[_PB]  # difference of the gradients first: the heights share angles
    var = np.einsum("kjm,j->km", dG * dG, sigma * sigma)
    return e, np.sqrt(var), valid


def height_statistic(
    sensors: Mat,
    az: F64,
    el: F64,
    sigma_azimuth: Vec,
    sigma_elevation: Vec,
) -> tuple[F64, F64, NDArray[np.bool_]]:
    """The six height differences of candidate triples and their first-order std.

    ``az``, ``el``: ``(m, 3)`` angles of each candidate's three measurements.  Returns
    ``e`` ``(m, 6)`` with ``e_ab = h_a − h_b`` over :data:`HEIGHT_PAIRS`,
    ``σ(e_ab)² = Σ_n σ_n² (g_a − g_b)_n²`` (``g_a = ∇_θ h_a``,
    ``σ = (σ_α1, σ_α2, σ_α3, σ_ε1, σ_ε2, σ_ε3)``), and ``valid`` ``(m,)``: False where a pair's
    projected LOS are parallel (``|D_ij| < PARALLEL_EPS``), which cannot be tested.
    """
    az = np.asarray(az, dtype=np.float64).reshape(-1, 3)
    el = np.asarray(el, dtype=np.float64).reshape(-1, 3)
    sigma = np.concatenate([np.broadcast_to(sigma_azimuth, 3), np.broadcast_to(sigma_elevation, 3)])
    e, se, valid = _height_diffs(
        np.asarray(sensors, dtype=np.float64), np.cos(az), np.sin(az), np.tan(el), sigma
    )
    return e.T, se.T, valid


def elevation_candidates(
    scan: PassiveScan,
    Q: Index,
    params: AssocParams,
    _pre: tuple[F64, F64, F64, F64, Index] | None = None,
) -> tuple[Index, F64]:
    """The elevation test on the candidates ``Q`` ``(q, 3)``: keep the triples with
    ``|e_ab| ≤ gate · σ(e_ab)`` for all six differences (and a testable geometry).

    Returns ``P`` ``(m, 3)`` and the cost ``Ψ`` ``(m,)``: ``Ψ = (1/6) Σ_ab |e_ab|`` (km, raw, the
    paper's) or ``Σ_ab |e_ab| / σ_ab`` (``params.cot_cost == "normalised"``).
    """
    cs, ns, _, ts, off = _per_measurement(scan) if _pre is None else _pre
    gid = Q + off
    c, n, t = cs[gid], ns[gid], ts[gid]
    sigma = np.concatenate([params.sigma_azimuth, params.sigma_elevation])
    e, se, valid = _height_diffs(scan.sensors, c, n, t, sigma)
    ae = np.abs(e)
    keep = valid & np.all(ae <= params.gate * se, axis=0)
    if params.cot_cost == "normalised":
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(se > 0, ae / np.where(se > 0, se, 1.0), np.where(ae > 0, np.inf, 0.0))
        psi = ratio.sum(axis=0)
    else:
        psi = ae.mean(axis=0)
    return Q[keep], psi[keep]


def _per_measurement(scan: PassiveScan) -> tuple[F64, F64, F64, F64, Index]:
    """Pipeline step 1, once per measurement: ``cos α``, ``sin α``, ``k = cot α``, ``tan ε``
    of all measurements concatenated (sensor 1's, then 2's, then 3's), and the offsets ``(3,)``
    of each sensor's block."""
    z = np.concatenate(scan.z)
    c, n = np.cos(z[:, 0]), np.sin(z[:, 0])
    with np.errstate(divide="ignore", invalid="ignore"):
        k = c / n
    n1, n2, _ = scan.counts
    return c, n, k, np.tan(z[:, 1]), np.array([0, n1, n1 + n2])


# --------------------------------------------------------------------------------------------
# §6 indicator-function analysis
# --------------------------------------------------------------------------------------------


def indicator_analysis(P: Index, psi: F64) -> Index:
    """Resolve conflicts between candidate rows ``P`` ``(m, 3)`` with costs ``Ψ`` ``(m,)``.

    ``ξ(i, n)`` = number of live rows holding measurement ``n`` of sensor ``i``.  Repeat while a
    row is live: recompute ξ; the *forced* rows hold at least one measurement with ``ξ = 1``;
    accept ``r* = argmin Ψ`` over the forced rows if any (paper case 1, cheapest first), else
    over all live rows (case 2); kill ``r*`` and every live row sharing a measurement with it.

    Returns the accepted row indices into ``P``, in acceptance order.  The accepted rows are
    pairwise disjoint; barring exact cost ties the set does not depend on the order of ``P``'s
    rows or of the measurement lists.
    """
    P = np.asarray(P, dtype=np.intp)
    m = P.shape[0]
    if m == 0:
        return np.zeros(0, dtype=np.intp)
    psi = np.asarray(psi, dtype=np.float64)
    # one global id per (sensor, measurement): ξ is then one bincount over the live rows
    size = P.max(axis=0) + 1
    gid = P + np.concatenate([[0], np.cumsum(size[:2])])
    n_ids = int(size.sum())
    used = np.zeros(n_ids, dtype=bool)
    live = np.ones(m, dtype=bool)
    chosen: list[int] = []
    while True:
        xi = np.bincount(gid[live].reshape(-1), minlength=n_ids)
        if xi.max() <= 1:
            # the live rows are pairwise disjoint, hence all forced: the loop would accept them
            # one by one, cheapest first (argmin: first index among ties), killing nothing else
            rest = np.flatnonzero(live)
            chosen += rest[np.argsort(psi[rest], kind="stable")].tolist()
            return np.asarray(chosen, dtype=np.intp)
        # a live row counts itself, so its smallest ξ is 1 exactly when it is forced
        forced = live & (np.minimum.reduce(xi[gid], axis=1) == 1)
        pool = forced if forced.any() else live
        r = int(np.argmin(np.where(pool, psi, np.inf)))
        chosen.append(r)
        used[gid[r]] = True
        live &= ~np.logical_or.reduce(used[gid], axis=1)
        if not live.any():
            return np.asarray(chosen, dtype=np.intp)


# --------------------------------------------------------------------------------------------
# §7 the pipeline
# --------------------------------------------------------------------------------------------


def associate_cot(scan: PassiveScan, params: AssocParams) -> Association:
    """The complete cot method (spec §7): azimuth test, elevation test, indicator analysis.

    ``info``: ``n_triples`` (n1 n2 n3), ``n_azimuth`` (|Q|), ``n_elevation`` (|P|).
    """
    n1, n2, n3 = scan.counts
    if n1 * n2 * n3 == 0:
        return Association.empty(n_triples=0, n_azimuth=0, n_elevation=0)
    pre = _per_measurement(scan)
    if params.azimuth_form == "cot":
        k = pre[2]
        x, y = scan.sensors[:, 0], scan.sensors[:, 1]
        with np.errstate(invalid="ignore", over="ignore"):
            F, var = _cot_stat(
                x,
                y,
                k[:n1, None, None],
                k[n1 : n1 + n2][None, :, None],
                k[n1 + n2 :][None, None, :],
                params.sigma_azimuth**2,
            )
            keep = F * F <= params.gate**2 * var
        Q = np.argwhere(keep)
    else:
        Q = azimuth_candidates(scan, params)[0]
    P, psi = elevation_candidates(scan, Q, params, pre)
    rows = indicator_analysis(P, psi)
    Z = P[rows]
    info = {"n_triples": n1 * n2 * n3, "n_azimuth": int(Q.shape[0]), "n_elevation": int(P.shape[0])}
    return Association(Z, Z, float(psi[rows].sum()), 0, "ok", info)
