"""Dual lower bounds of the norm metrics over a branch-and-bound node's reduced information
interval (:class:`_DualBound`; spectral, one_norm, inf_norm, abs_trace with ``r = 2``).

**The relaxation.**  A node's completions have information ``Z ∈ [Z_lo, Z_hi]`` (Loewner,
``r x r``) and covariance ``P = P∞ + K W Kᵀ`` with ``W = Z⁻¹ ∈ [W_lo, W_hi] = [Z_hi⁻¹, Z_lo⁻¹]``
(inversion is Loewner-antitone), i.e. ``W = W_lo + R X R`` with ``R = (W_hi - W_lo)^½`` and
``0 ⪯ X ⪯ I``.  ``P`` is *affine* in ``W``: ``P - P_d = M(X) = M_lo + V X Vᵀ`` with ``M_lo =
P(W_lo) - P_d`` (the interval's lower endpoint ``A`` less ``P_d``) and ``V = K R`` (``n x r``).
A norm of ``P - P_d`` is therefore convex in ``X``, and its minimum over this 3-dimensional set
(``r = 2``) is, on the paper-like problems, within a fraction of a per cent of the best subset
(the Loewner interval of the covariances has ``n(n+1)/2`` dimensions and loses 40 %).

**The certificate (weak duality).**  Every norm is the support function of its dual ball:
``||M|| = max_{Y ∈ B*} <Y, M>``.  So for *any* ``Y ∈ B*`` and every completion::

    ||M(X)|| >= <Y, M_lo> + <Vᵀ Y V, X> >= <Y, M_lo> + Σ_k min(μ_k(Vᵀ Y V), 0) =: φ(Y),

(the minimum of the linear function ``<G, X>`` over ``0 ⪯ X ⪯ I`` is the sum of ``G``'s negative
eigenvalues ``μ_k``: write ``G = Σ μ_k u_k u_kᵀ``, ``<G, X> = Σ μ_k u_kᵀ X u_k`` with ``u_kᵀ X
u_k ∈ [0, 1]``, attained at the projector onto the negative eigenvectors).  ``φ(Y)`` is a valid
lower bound whatever ``Y`` is, as long as it is in the dual ball: how ``Y`` is found affects only
how tight the bound is, never its validity.  The dual balls (``<Y, M> = <(Y + Yᵀ)/2, M>`` for
symmetric ``M``):

- **spectral** ``||M||_2``: the nuclear-norm ball ``Σ |λ_i(Y)| <= 1``;
- **one_norm / inf_norm** (max column / row sum of ``|M|``; equal for symmetric ``M``): the
  convex hull of the atoms ``s e_jᵀ``, ``s ∈ {±1}^n`` (``||M||_1 = max_j max_s sᵀ M e_j``);
- **abs_trace** ``Σ_i |M_ii|``: the convex hull of the atoms ``diag(s)``, ``s ∈ {±1}^n``.

**Finding ``Y``.**  The epigraph problem ``min t`` s.t. ``t >= ||M(X)||``, ``0 ⪯ X ⪯ I`` is, in
the four variables ``(t, X)``, a tiny semidefinite program (spectral: ``tI ∓ M(X) ⪰ 0``) or linear
program (atoms: ``t >= <Y_a, M(X)>`` for every atom), solved by a barrier method batched over the
nodes: damped Newton steps on ``s t - Σ log det(constraints) - log det X - log det(I - X)``
(self-concordant: the damped step ``1/(1 + λ)``, ``λ`` the Newton decrement, stays strictly
feasible), ``s`` raised ``BARRIER_RAISE``-fold whenever ``λ < 1/2``.  The barrier's multipliers
give ``Y``: ``(tI - M)⁻¹ - (tI + M)⁻¹`` divided by its nuclear norm (spectral), or the atoms
weighted by ``1/(t - <Y_a, M>)`` and normalised to sum 1 (a convex combination of atoms): both in
the dual ball by construction.  A node stops once its bound, after the deflation below, exceeds
the threshold (pruned) or the primal value ``||M(X)||`` at the current ``X`` is at most it
(no bound over the node can prune it).

**Vertex bound** (:meth:`_DualBound.vertex_bound`; one_norm, inf_norm, abs_trace in exact mode,
on the nodes the barrier does not refine, and before the barrier on the others).  The barrier is too
slow for most nodes of an exact search (0.1-1 ms a node), but ``φ(Y)`` is a valid bound for
*any* ``Y`` in the dual ball, in particular for a few points found per node in closed form:

*Column points* (:func:`column_ascent`).  For the induced norms the dual ball contains
``sym(y e_jᵀ)`` for every column ``j`` and every ``y ∈ [-1, 1]^n`` (``y e_jᵀ`` is a convex
combination of the atoms ``s e_jᵀ``: the box is the convex hull of the sign vectors).  With ``a
= Vᵀ y`` and ``v_j = Vᵀ e_j`` (row ``j`` of ``V``), ``Vᵀ sym(y e_jᵀ) V = ½(a v_jᵀ + v_j aᵀ)``,
whose eigenvalues are ``½(a·v_j ± |a| |v_j|)`` (the larger ``>= 0``), so::

    φ(sym(y e_jᵀ)) = y · M_lo e_j + ½ a·v_j - ½ |a| |v_j| = b_j · y - ρ_j |Vᵀ y| =: h_j(y),

``b_j = M_mid e_j`` the column of ``M`` at the node's middle ``M_mid = M_lo + ½ V Vᵀ`` (``X =
I/2``) and ``ρ_j = |v_j| / 2``.  ``h_j`` is concave; its maximum over the box is ``min_{|u| <=
1} ||b_j - ρ_j V u||_1`` (minimax), generally with fractional ``y`` where an entry of column
``j`` changes sign over the node: the signs ``y = sign(b_j)`` alone (the seventh round's vertex
bound) left the bound 0.8 % under the threshold on the walked nodes of one_norm's N = 40
problem 3, where the node's optimal ``Y`` (the barrier's) mixes two sign patterns or two
columns.  :func:`column_ascent` starts from ``sign(b_j)`` and maximises ``h_j`` exactly in one
coordinate ``y_i = t`` at a time: with the others fixed, ``Vᵀ y = p + t w`` (``w`` row ``i`` of
``V``, ``p`` the rest), written ``p = α ŵ + γ ŵ⊥`` (``ŵ = w/|w|``, ``γ >= 0``)::

    h(t) = β t - ρ sqrt((α + t|w|)² + γ²) + const,   β = b_ji,

``h'(t) = β - ρ|w| (α + t|w|) / sqrt((α + t|w|)² + γ²)``; with ``c = β / (ρ|w|)``: if ``|c| >=
1`` ``h`` is monotone (the sign of ``β``) and ``t = sign(β)``; else ``h' = 0`` at ``α + t|w| =
c γ / sqrt(1 - c²)`` and, ``h`` being concave, the maximum over ``[-1, 1]`` is that ``t``
clipped (``γ = 0``: the kink ``t = -α/|w|``).  The result is clipped to the box, so whatever
the arithmetic did the point is in the dual ball; the bound is ``h_j`` recomputed from the
final ``y`` (the identity above; its rounding is that of ``φ``, covered below).  *Mixtures*
(:func:`column_bound`): a convex combination of two points of the ball is in it, and ``φ(w Y_j
+ (1 - w) Y_k) = w l_j + (1 - w) l_k + negsum(w G_j + (1 - w) G_k)`` (``l_j = y_j · M_lo e_j``,
``G_j = ½(a v_jᵀ + v_j aᵀ)``) is concave in ``w``: a few golden-section steps on the two best
columns.  Measured on the walked nodes (fewer than 16 undecided sensors) of one_norm's N = 40
problem 3 (`covnet bench search` problems): the signs alone prune 0.05 % of them, the ascent
(2 sweeps) 42 %, with the mixture 48 %, the barrier's optimum 58 %; and the share whose
subtree's optimum lies above the threshold, which a bound over the completions could prune,
100 %.

*Diagonal points* (:func:`diagonal_ascent`; abs_trace).  abs_trace's dual ball is the hull of
the ``diag(s)``, i.e. every ``diag(y)`` with ``y ∈ [-1, 1]^n``, and with ``v_i`` row ``i`` of
``V``::

    φ(diag(y)) = Σ_i y_i M_lo,ii + negsum(G(y)),   G(y) = Σ_i y_i v_i v_iᵀ   (2 x 2),

concave in ``y`` (a linear term plus ``negsum = min_{0 ⪯ X ⪯ I} <·, X>``, a minimum of linear
functions).  Its maximum over the box is the relaxation's optimum ``min_X Σ_i |M(X)_ii|``
(minimax: the box and ``{0 ⪯ X ⪯ I}`` are compact and convex), which the barrier reaches at
0.1-1 ms a node; coordinate ascent reaches it, or nearly, for a few µs.  One coordinate ``y_i =
t`` with the others fixed: ``G = G_0 + t w wᵀ`` (``w = v_i``, ``G_0`` the rest), ``f(t) = β t +
negsum(G_0 + t w wᵀ)`` with ``β = M_lo,ii``, concave, ``f'(t) = β + Σ_{μ_k < 0} (u_kᵀ w)²``
(``μ_k, u_k`` the eigenpairs of ``G``; each term in ``[0, |w|²]``, together at most
``|w|²``).  So ``β >= 0`` gives ``t = 1`` and ``β + |w|² <= 0`` gives ``t = -1``.  Otherwise, in
the basis ``ŵ = w/|w|``, ``ŵ⊥``, ``G = [[p + t|w|², q], [q, r]]``; with ``p' = p + t|w|²`` and
``x = (p' - r)/2``, exactly one eigenvalue is negative for ``p' > q²/r`` (``r < 0``; below, both
are: ``f' = β + |w|² > 0``) or ``p' < q²/r`` (``r > 0``; above, none is: ``f' = β < 0``) or
every ``p'`` (``r = 0 ≠ q``), and there ``f' = β + |w|² (1 - x / sqrt(x² + q²)) / 2``, decreasing
in ``p'``, zero at ``x = s|q| / sqrt(1 - s²)``, ``s = 1 + 2β/|w|² ∈ (-1, 1)``.  Hence the
maximiser is ``p'* = r + 2x`` raised to ``q²/r`` (``r < 0``) or lowered to it (``r > 0``), and
``t = (p'* - p)/|w|²`` clipped to ``[-1, 1]`` (``q = 0``: the kink ``p' = 0``, which the same
formula gives).  The start is the signs of the diagonal at the node's middle (the seventh
round's point, which alone pruned 3 % of the sampled nodes below), the result is clipped to
the box (so ``diag(y)`` is in the dual ball whatever the arithmetic) and ``φ`` is recomputed from
the final ``y`` (its rounding is that of ``φ``, below).  Measured on the walked nodes with 3-16
undecided sensors of abs_trace's N = 40 problem 3 (842 sampled): the interval bound prunes none
of them (they are walked), the box maximum (the barrier run to the end) all of them (median
2.7 % above the threshold), the ascent from the signs 3 % with no sweep, 99.3 % with one,
100 % with two.

**Rounding.**  As the interval bounds (:mod:`covnet.core.allocation.interval_bounds`): the
computed ``M_lo``, the interval's endpoints and the completion's computed ``P`` are each within
``err`` entrywise of the exact ones; an entrywise error ``E`` changes ``<Y, ·>`` by at most
``Σ|Y_ij| err <= n err`` on each of the three dual balls (nuclear: ``Σ|Y_ij| <= n ||Y||_F <= n
||Y||_*``; columns: ``Σ_j max_i |Y_ij| <= 1``; diagonal: ``|y_i| <= 1``) and the metric of the
computed ``P`` by at most its norm ``<= n err``: ``3 n err`` in all.  The bound's own arithmetic
(and the normalisation of ``Y``) is allowed a relative ``ROUND n² eps`` of the value and of ``n``
times the input scale.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal, Protocol

import numpy as np
from numpy.typing import NDArray

from covnet.core.allocation.interval_bounds import ROUND, IntervalContext
from covnet.core.allocation.relaxation import _eig2, _inv2, _s2, _sqrt2
from covnet.core.gaussian import Mat

EPS = float(np.finfo(np.float64).eps)

#: damped Newton steps of the barrier method per node (each also gives a bound)
BARRIER_ITERS = 30
#: the barrier weight ``s`` is multiplied by this once a step is near the central path
BARRIER_RAISE = 6.0
#: ... once the Newton decrement is below this
NEAR_CENTRAL = 1.0
#: atoms are enumerated (``n 2^n`` of them for the induced norms) up to this state dimension
ATOMS_MAX_N = 8


@dataclass(frozen=True)
class DualNorm:
    """A metric that is a norm of ``P - P_d`` with a known dual ball (the metric entry's
    ``dual_bound``, :mod:`covnet.core.metrics`): ``kind`` ``"spectral"`` (the nuclear-norm ball)
    or ``"atoms"`` (the convex hull of ``atoms(n)`` ``(a, n, n)``, each of dual norm 1)."""

    name: str
    kind: Literal["spectral", "atoms"]
    atoms: Callable[[int], Mat] | None = None
    #: the vertex bound before its rounding allowance, from a node's ``M_lo`` ``(m, n, n)`` and
    #: ``V`` ``(m, n, 2)`` (finite): ``(m,)``, the best ``φ(Y)`` over a few dual points ``Y``
    #: in the dual ball; ``None``: no vertex bound (module docstring)
    vertices: Callable[[Mat, Mat], Mat] | None = None
    #: exact mode: the vertex bound on the nodes with at least this many undecided sensors
    #: (below the barrier's ``DUAL_MIN_REST``; :mod:`covnet.core.allocation.search`), CPU
    #: clock at N = 40: one_norm's problem 0 0.86 M nodes and 3.8 s with 1, 1.0 M / 3.8 s with
    #: 4, 1.8 M / 4.2 s with 8, 2.7 M / 5.5 s with 12; abs_trace's five bench problems and four
    #: tie problems (N = 32, 40), two alternated rounds: 4.0-4.2 s in all with 1, 3.4-3.5 with
    #: 4, 2.8 with 8 and 12, 3.5-3.6 with 16 (the same subsets, values and bits)
    vertex_min_rest: int = 1


def _signs(n: int) -> Mat:
    """Every ``s ∈ {±1}^n`` ``(2^n, n)``."""
    idx = np.arange(2**n)[:, None] >> np.arange(n)[None, :]
    return np.where(idx & 1, -1.0, 1.0)


def column_atoms(n: int) -> Mat:
    """``s e_jᵀ`` for every column ``j`` and sign vector ``s`` ``(n 2^n, n, n)``: ``||M||_1 =
    max_j Σ_i |M_ij| = max_{j, s} <s e_jᵀ, M>``."""
    S = _signs(n)
    out = np.zeros((n, S.shape[0], n, n))
    for j in range(n):
        out[j, :, :, j] = S
    return out.reshape(n * S.shape[0], n, n)


def diagonal_atoms(n: int) -> Mat:
    """``diag(s)`` for every sign vector ``s`` ``(2^n, n, n)``: ``Σ_i |M_ii| = max_s <diag(s),
    M>``."""
    S = _signs(n)
    out = np.zeros((S.shape[0], n, n))
    out[:, np.arange(n), np.arange(n)] = S
    return out


#: coordinate sweeps of :func:`column_ascent` (N = 40, one_norm's problem 3: the share of the
#: walked nodes below 16 undecided sensors that the points prune: 0 sweeps 0.05 %, 1: 40 %,
#: 2: 42 %, 10: 43 %; the barrier's optimal point: 58 %)
ASCENT_SWEEPS = 2


def column_ascent(M_lo: Mat, V: Mat, sweeps: int = ASCENT_SWEEPS) -> tuple[Mat, Mat]:
    """For every column ``j`` a ``y_j ∈ [-1, 1]^n`` (``y[:, j, :]``, ``(m, n, n)``) that
    increases ``h_j(y) = b_j · y - ρ_j |Vᵀ y| = φ(sym(y e_jᵀ))`` (module docstring, *column
    points*), and ``h_j(y_j)`` ``(m, n)``: from the signs of ``b_j`` (column ``j`` at the node's
    middle), ``sweeps`` rounds of exact maximisation coordinate by coordinate (closed form).
    Every ``y_j`` is in the box whatever the input (a non-finite step keeps the coordinate; a
    final clip), so ``sym(y_j e_jᵀ)`` is in the dual ball.  Inputs finite."""
    # coordinate-major layouts (contiguous per coordinate i): bt[i][:, j] = b_j[i] (M_mid is
    # symmetric), yt[i][:, j] = y_j[i], w0[i], w1[i] the row i of V
    bt = np.ascontiguousarray(np.moveaxis(M_lo + 0.5 * (V @ np.swapaxes(V, 1, 2)), 1, 0))
    rho = 0.5 * np.sqrt((V * V).sum(axis=2))  # (m, j)
    yt = np.where(bt < 0.0, -1.0, 1.0)
    n = bt.shape[0]
    w0 = np.ascontiguousarray(V[:, :, 0].T)[:, :, None]  # (i, m, 1)
    w1 = np.ascontiguousarray(V[:, :, 1].T)[:, :, None]
    with np.errstate(all="ignore"):
        a0 = (yt * w0).sum(axis=0)  # Vᵀ y_j (m, j), two components
        a1 = (yt * w1).sum(axis=0)
        steps = []
        for i in range(n):  # what does not depend on y: c = β / (ρ|w|) and the step's form
            wn = np.sqrt(w0[i] * w0[i] + w1[i] * w1[i])  # (m, 1)
            wn1 = np.where(wn > 0.0, wn, 1.0)
            rw = rho * wn
            beta = bt[i]
            c = np.where(rw > 0.0, beta / np.where(rw > 0.0, rw, 1.0), 2.0 * np.sign(beta))
            inside = np.abs(c) < 1.0
            cc = np.where(inside, c, 0.0)
            k = cc / np.sqrt(1.0 - cc * cc)
            edge = np.where(c >= 1.0, 1.0, -1.0)
            steps.append((w0[i] / wn1, w1[i] / wn1, wn1, k, inside, edge))
        for _ in range(sweeps):
            for i in range(n):
                u0, u1, wn1, k, inside, edge = steps[i]
                yi = yt[i]
                p0 = a0 - yi * w0[i]  # Vᵀ y without coordinate i
                p1 = a1 - yi * w1[i]
                alpha = p0 * u0 + p1 * u1
                gamma = np.abs(p0 * u1 - p1 * u0)
                t = np.where(inside, np.clip((k * gamma - alpha) / wn1, -1.0, 1.0), edge)
                t = np.where(np.isfinite(t), t, yi)
                yt[i] = t
                a0 = p0 + t * w0[i]
                a1 = p1 + t * w1[i]
    yt = np.clip(np.where(np.isfinite(yt), yt, 0.0), -1.0, 1.0)
    a0 = (yt * w0).sum(axis=0)
    a1 = (yt * w1).sum(axis=0)
    h = (bt * yt).sum(axis=0) - rho * np.sqrt(a0 * a0 + a1 * a1)
    y = np.ascontiguousarray(np.moveaxis(yt, 0, 2))  # (m, j, i)
    return np.asarray(y, dtype=np.float64), np.asarray(h, dtype=np.float64)


#: golden-section steps of the mixture of the two best column points (:func:`column_bound`)
MIX_STEPS = 8
_GOLD = 0.5 * (math.sqrt(5.0) - 1.0)


def _negsum_h(g0: Mat, g1: Mat, g2: Mat) -> Mat:
    """The sum of the negative eigenvalues of ``[[g0, g1], [g1, g2]]``."""
    h = 0.5 * (g0 + g2)
    q = np.hypot(0.5 * (g0 - g2), g1)
    return np.minimum(h + q, 0.0) + np.minimum(h - q, 0.0)


def column_bound(M_lo: Mat, V: Mat, steps: int | None = None) -> Mat:
    """The best ``φ`` ``(m,)`` over the column points ``Y_j = sym(y_j e_jᵀ)`` of
    :func:`column_ascent` and the mixtures ``w Y_j + (1 - w) Y_k`` of the two best (``w`` by
    ``steps`` golden-section steps on ``[0, 1]``; ``φ`` is concave in ``w``), before the
    rounding allowance (module docstring, *column points*).  ``φ(Y_j) = h_j`` and ``φ`` of a
    mixture ``w l_j + (1 - w) l_k + negsum(w G_j + (1 - w) G_k)`` with ``l_j = y_j · M_lo e_j``
    and ``G_j = Vᵀ Y_j V = ½(a v_jᵀ + v_j aᵀ)``, ``a = Vᵀ y_j``, ``v_j = Vᵀ e_j``."""
    steps = MIX_STEPS if steps is None else steps
    y, h = column_ascent(M_lo, V)
    best = h.max(axis=1)
    if steps <= 0 or h.shape[1] < 2:
        return np.asarray(best, dtype=np.float64)
    m = h.shape[0]
    rows = np.arange(m)
    order = np.argsort(-np.where(np.isfinite(h), h, -np.inf), axis=1, kind="stable")
    pts = []
    for j in (order[:, 0], order[:, 1]):
        yj = y[rows, j]  # (m, n)
        vj = V[rows, j]  # (m, 2)
        a = np.einsum("mi,mia->ma", yj, V)
        lj = np.einsum("mi,mi->m", yj, M_lo[rows, :, j])
        g = (
            a[:, 0] * vj[:, 0],
            0.5 * (a[:, 0] * vj[:, 1] + a[:, 1] * vj[:, 0]),
            a[:, 1] * vj[:, 1],
        )
        pts.append((lj, g))
    (l1, g1), (l2, g2) = pts

    def phi(w: Mat) -> Mat:
        u = 1.0 - w
        return np.asarray(
            w * l1
            + u * l2
            + _negsum_h(w * g1[0] + u * g2[0], w * g1[1] + u * g2[1], w * g1[2] + u * g2[2]),
            dtype=np.float64,
        )

    lo, hi = np.zeros(m), np.ones(m)
    x1 = hi - _GOLD * (hi - lo)
    x2 = lo + _GOLD * (hi - lo)
    f1, f2 = phi(x1), phi(x2)
    best = np.fmax(best, np.fmax(f1, f2))
    with np.errstate(all="ignore"):
        for _ in range(steps):
            left = f1 >= f2  # the maximum of a concave function: in [lo, x2]
            hi = np.where(left, x2, hi)
            lo = np.where(left, lo, x1)
            xn = np.where(left, hi - _GOLD * (hi - lo), lo + _GOLD * (hi - lo))
            fn = phi(xn)
            best = np.fmax(best, fn)
            x1, x2, f1, f2 = (
                np.where(left, xn, x2),
                np.where(left, x1, xn),
                np.where(left, fn, f2),
                np.where(left, f1, fn),
            )
    return np.asarray(best, dtype=np.float64)


#: coordinate sweeps of :func:`diagonal_ascent` (N = 40, abs_trace's problem 3, the sampled
#: walked nodes with 3-16 undecided sensors: see the module docstring, *diagonal points*)
DIAG_SWEEPS = 2


def diagonal_ascent(M_lo: Mat, V: Mat, sweeps: int | None = None) -> tuple[Mat, Mat]:
    """A ``y ∈ [-1, 1]^n`` ``(m, n)`` per node that increases ``φ(diag(y)) = Σ_i y_i M_lo,ii +
    negsum(Σ_i y_i v_i v_iᵀ)`` (module docstring, *diagonal points*), and that ``φ`` ``(m,)``
    recomputed from the final ``y``: from the signs of the diagonal at the node's middle,
    ``sweeps`` rounds of exact maximisation coordinate by coordinate (closed form).  ``y`` is
    in the box whatever the input (a non-finite step keeps the coordinate; a final clip), so
    ``diag(y)`` is in abs_trace's dual ball.  Inputs finite."""
    sweeps = DIAG_SWEEPS if sweeps is None else sweeps
    n = M_lo.shape[-1]
    beta = [np.ascontiguousarray(M_lo[:, i, i]) for i in range(n)]
    w0 = [np.ascontiguousarray(V[:, i, 0]) for i in range(n)]
    w1 = [np.ascontiguousarray(V[:, i, 1]) for i in range(n)]
    with np.errstate(all="ignore"):
        y = []
        g0 = np.zeros(M_lo.shape[0])
        g1 = np.zeros(M_lo.shape[0])
        g2 = np.zeros(M_lo.shape[0])
        steps = []
        for i in range(n):
            ww = w0[i] * w0[i] + w1[i] * w1[i]
            mid = beta[i] + 0.5 * ww  # M_mid,ii
            yi = np.where(mid < 0.0, -1.0, 1.0)
            y.append(yi)
            g0 = g0 + yi * (w0[i] * w0[i])
            g1 = g1 + yi * (w0[i] * w1[i])
            g2 = g2 + yi * (w1[i] * w1[i])
            # what does not depend on y: the case (β >= 0: t = 1; β + |w|² <= 0: t = -1) and
            # k = s / sqrt(1 - s²), s = 1 + 2β/|w|²
            ww1 = np.where(ww > 0.0, ww, 1.0)
            inside = (beta[i] < 0.0) & (beta[i] + ww > 0.0)
            s = np.where(inside, 1.0 + 2.0 * beta[i] / ww1, 0.0)
            k = s / np.sqrt(1.0 - s * s)
            wn = np.sqrt(ww1)
            edge = np.where(beta[i] >= 0.0, 1.0, -1.0)
            steps.append((w0[i] / wn, w1[i] / wn, ww1, k, inside, edge))
        for _ in range(sweeps):
            for i in range(n):
                u0, u1, ww1, k, inside, edge = steps[i]
                yi = y[i]
                a, b, c = w0[i] * w0[i], w0[i] * w1[i], w1[i] * w1[i]
                h0, h1, h2 = g0 - yi * a, g1 - yi * b, g2 - yi * c  # G without coordinate i
                uu = u0 * u1
                p = u0 * u0 * h0 + 2.0 * uu * h1 + u1 * u1 * h2
                r = u1 * u1 * h0 - 2.0 * uu * h1 + u0 * u0 * h2
                q = uu * (h2 - h0) + (u0 * u0 - u1 * u1) * h1
                ps = r + 2.0 * k * np.abs(q)
                lim = q * q / np.where(r != 0.0, r, 1.0)
                ps = np.where(
                    r < 0.0, np.maximum(ps, lim), np.where(r > 0.0, np.minimum(ps, lim), ps)
                )
                t = np.where(inside, np.clip((ps - p) / ww1, -1.0, 1.0), edge)
                t = np.where(np.isfinite(t), t, yi)
                y[i] = t
                g0, g1, g2 = h0 + t * a, h1 + t * b, h2 + t * c
        yb = np.clip(
            np.where(np.isfinite(np.stack(y, axis=1)), np.stack(y, axis=1), 0.0), -1.0, 1.0
        )
        lin = yb[:, 0] * beta[0]
        g0 = yb[:, 0] * (w0[0] * w0[0])
        g1 = yb[:, 0] * (w0[0] * w1[0])
        g2 = yb[:, 0] * (w1[0] * w1[0])
        for i in range(1, n):
            lin = lin + yb[:, i] * beta[i]
            g0 = g0 + yb[:, i] * (w0[i] * w0[i])
            g1 = g1 + yb[:, i] * (w0[i] * w1[i])
            g2 = g2 + yb[:, i] * (w1[i] * w1[i])
        phi = lin + _negsum_h(g0, g1, g2)
    return np.asarray(yb, dtype=np.float64), np.asarray(phi, dtype=np.float64)


def diagonal_bound(M_lo: Mat, V: Mat) -> Mat:
    """abs_trace's vertex bound before the rounding allowance ``(m,)``: ``φ(diag(y))`` at the
    point of :func:`diagonal_ascent`."""
    return diagonal_ascent(M_lo, V)[1]


SPECTRAL_DUAL = DualNorm("spectral", "spectral")
ONE_NORM_DUAL = DualNorm("one_norm", "atoms", column_atoms, column_bound)
# the same for symmetric P - P_d
INF_NORM_DUAL = DualNorm("inf_norm", "atoms", column_atoms, column_bound)
ABS_TRACE_DUAL = DualNorm("abs_trace", "atoms", diagonal_atoms, diagonal_bound, 8)


class _Reduced(Protocol):
    """What the bound reads of its problem (:class:`~covnet.core.allocation.search_problem.\
_Problem`): the reduced form ``P(W) = P∞ + K W Kᵀ`` (``T`` flattened), ``P_d``, the error
    model."""

    n: int
    D: Mat
    Kmat: Mat
    P_inf: Mat
    T: Mat
    ctx: IntervalContext


#: the symmetric 2 x 2 basis of ``X = [[x0, x1], [x1, x2]]``
_BASIS2 = np.array([[[1.0, 0.0], [0.0, 0.0]], [[0.0, 1.0], [1.0, 0.0]], [[0.0, 0.0], [0.0, 1.0]]])


def _negsum_sym2(a: Mat, b: Mat, c: Mat) -> Mat:
    l1, l2, _, _ = _eig2(a, b, c)
    return np.minimum(l1, 0.0) + np.minimum(l2, 0.0)


class _DualBound:
    """Dual lower bounds of a norm metric over nodes ``[Z_lo, Z_hi]`` (module docstring)."""

    def __init__(self, prob: _Reduced, dual: DualNorm) -> None:
        self.prob = prob
        self.dual = dual
        n = prob.n
        self.n = n
        self.Dflat = prob.D.reshape(n * n)
        self.K = prob.Kmat
        if dual.kind == "atoms":
            if dual.atoms is None or n > ATOMS_MAX_N:
                raise ValueError(f"no atoms for {dual.name} at n = {n}")
            self.atoms = np.asarray(dual.atoms(n), dtype=np.float64)
            sym = 0.5 * (self.atoms + np.swapaxes(self.atoms, 1, 2))
            self.atoms_flat = sym.reshape(-1, n * n)
        self.rel = ROUND * n * n * EPS

    # -- the pieces -------------------------------------------------------------------------

    def _setup(self, Z_lo: Mat, Z_hi: Mat) -> tuple[Mat, Mat]:
        """``M_lo`` ``(m, n, n)`` and ``V = K R`` ``(m, n, 2)``."""
        n = self.n
        w_lo = _inv2(*_s2(Z_hi))
        w_hi = _inv2(*_s2(Z_lo))
        r = _sqrt2(w_hi[0] - w_lo[0], w_hi[1] - w_lo[1], w_hi[2] - w_lo[2])
        W_lo = np.stack((w_lo[0], w_lo[1], w_lo[1], w_lo[2]), axis=1)
        M_lo = (W_lo @ self.prob.T + (self.prob.P_inf - self.Dflat)).reshape(-1, n, n)
        R = np.stack((r[0], r[1], r[1], r[2]), axis=1).reshape(-1, 2, 2)
        V = np.einsum("ia,mab->mib", self.K, R)
        return M_lo, V

    def phi(self, Y: Mat, M_lo: Mat, V: Mat) -> Mat:
        """``φ(Y) = <Y, M_lo> + Σ min(μ_k(Vᵀ Y V), 0)`` (``Y`` symmetric, in the dual ball):
        a lower bound of the exact norm over the node (module docstring), before rounding."""
        lin = np.einsum("mij,mij->m", Y, M_lo)
        G = np.einsum("mia,mij,mjb->mab", V, Y, V)
        return np.asarray(
            lin + _negsum_sym2(G[:, 0, 0], 0.5 * (G[:, 0, 1] + G[:, 1, 0]), G[:, 1, 1]),
            dtype=np.float64,
        )

    def final(self, phi: Mat) -> Mat:
        """``φ`` deflated by the model errors and the rounding (module docstring), ``>= 0``."""
        ctx = self.prob.ctx
        n = self.n
        v = np.maximum(phi, 0.0) * (1.0 - self.rel)
        v -= 3.0 * n * ctx.err + self.rel * n * ctx.scale
        out = np.maximum(v, 0.0)
        return np.where(np.isnan(out), 0.0, out)

    def _goal(self, tau: float) -> float:
        """The least ``φ`` whose :meth:`final` exceeds ``tau`` (the stopping rule only)."""
        if not math.isfinite(tau):
            return tau
        ctx, n = self.prob.ctx, self.n
        g = (tau + 3.0 * n * ctx.err + self.rel * n * ctx.scale) / (1.0 - self.rel)
        return g + 1e-12 * abs(g)

    # -- the barrier method -------------------------------------------------------------------

    def bound(
        self,
        Z_lo: Mat,
        Z_hi: Mat,
        tau: float = math.inf,
        stop: Callable[[], bool] | None = None,
    ) -> Mat:
        """Lower bounds ``(m,)`` of the metric over the nodes with information ``[Z_lo, Z_hi]``
        (rows ``(m, 4)``), ``0`` where nothing is proven.  ``stop`` (a time limit): the barrier
        iterations end once it says so (the bound so far: valid whatever ``Y`` was reached)."""
        m = Z_lo.shape[0]
        out = np.zeros(m)
        if m == 0:
            return out
        with np.errstate(all="ignore"):
            M_lo, V = self._setup(Z_lo, Z_hi)
            ok = np.isfinite(M_lo).all(axis=(1, 2)) & np.isfinite(V).all(axis=(1, 2))
            idx = np.flatnonzero(ok)
            vertices = self.dual.vertices
            if idx.size and vertices is not None and math.isfinite(tau):
                # the vertex bound first: the barrier only where it does not prune
                vb = self.final(vertices(M_lo[idx], V[idx]))
                out[idx] = np.where(np.isfinite(vb), vb, 0.0)
                idx = idx[~(out[idx] > tau)]
            if idx.size:
                out[idx] = np.fmax(out[idx], self._solve(M_lo[idx], V[idx], tau, stop))
        return out

    def vertex_bound(self, Z_lo: Mat, Z_hi: Mat) -> Mat:
        """The vertex bound ``(m,)`` over the nodes ``[Z_lo, Z_hi]``: the best :meth:`final`
        ``φ(Y)`` over the dual points ``vertices(M_mid)`` of :attr:`DualNorm.vertices`, ``M_mid
        = M_lo + ½ V Vᵀ`` the middle of the node (``X = I/2``); ``0`` without vertices or where
        nothing is proven.  Valid whatever the points are, as long as each is in the dual ball
        (module docstring)."""
        m = Z_lo.shape[0]
        out = np.zeros(m)
        vertices = self.dual.vertices
        if m == 0 or vertices is None:
            return out
        with np.errstate(all="ignore"):
            M_lo, V = self._setup(Z_lo, Z_hi)
            ok: NDArray[np.bool_] = np.asarray(
                np.isfinite(M_lo).all(axis=(1, 2)) & np.isfinite(V).all(axis=(1, 2))
            )
            M_lo = np.where(ok[:, None, None], M_lo, 0.0)
            V = np.where(ok[:, None, None], V, 0.0)
            out = self.final(vertices(M_lo, V))
        return np.where(np.isfinite(out) & ok, out, 0.0)

    def _solve(self, M_lo: Mat, V: Mat, tau: float, stop: Callable[[], bool] | None = None) -> Mat:
        m, n = M_lo.shape[0], self.n
        goal = self._goal(tau)
        # dM/dx_k = V B_k Vᵀ (m, 3, n, n)
        E = np.einsum("mia,kab,mjb->mkij", V, _BASIS2, V)
        atoms = self.dual.kind == "atoms"
        c: Mat | None = None
        q: Mat | None = None
        if atoms:
            c = M_lo.reshape(m, n * n) @ self.atoms_flat.T  # (m, a)
            q = np.einsum("mkp,ap->mak", E.reshape(m, 3, n * n), self.atoms_flat)  # (m, a, 3)
            nu = float(c.shape[1] + 4)
        else:
            nu = float(2 * n + 4)
        out = np.zeros(m)
        idx = np.arange(m)
        x = np.tile(np.array([0.5, 0.0, 0.5]), (m, 1))
        val = self._value(M_lo, E, x, c, q)
        t = val + 0.05 * np.abs(val) + 1e-9 * self.prob.ctx.scale + 1e-300
        s = nu / t
        eye = np.eye(n)
        for it in range(BARRIER_ITERS):
            # the time is up: this iteration's multipliers give the bound, then stop
            last = it == BARRIER_ITERS - 1 or (stop is not None and stop())
            # gradient and Hessian of s t + barrier in z = (t, x0, x1, x2)
            g = np.zeros((idx.size, 4))
            g[:, 0] = s
            H = np.zeros((idx.size, 4, 4))
            X = np.einsum("mk,kab->mab", x, _BASIS2)
            for F, sign in ((X, 1.0), (np.eye(2) - X, -1.0)):
                Fi = np.linalg.inv(F)
                T = sign * np.einsum("mab,kbc->mkac", Fi, _BASIS2)
                g[:, 1:] -= np.einsum("mkaa->mk", T)
                H[:, 1:, 1:] += np.einsum("mkab,mlba->mkl", T, T)
            Y = None
            Cis: list[Mat] | None = None
            if atoms:
                assert c is not None and q is not None
                f = t[:, None] - c - np.einsum("mak,mk->ma", q, x)
                a_ = np.concatenate((np.ones(f.shape + (1,)), -q), axis=2) / f[:, :, None]
                g -= a_.sum(axis=1)
                H += np.einsum("mak,mal->mkl", a_, a_)
            else:
                M = M_lo + np.einsum("mk,mkij->mij", x, E)
                Yd = []
                for sign in (1.0, -1.0):
                    C = t[:, None, None] * eye - sign * M
                    Ci = np.linalg.inv(C)
                    Yd.append(Ci)
                    dC = np.concatenate(
                        (np.broadcast_to(eye, (idx.size, 1, n, n)), -sign * E), axis=1
                    )
                    T = np.einsum("mab,mkbc->mkac", Ci, dC)
                    g -= np.einsum("mkaa->mk", T)
                    H += np.einsum("mkab,mlba->mkl", T, T)
                Y = Yd[0] - Yd[1]
                Cis = Yd
            try:
                step = np.asarray(-np.linalg.solve(H, g[:, :, None])[:, :, 0], dtype=np.float64)
            except np.linalg.LinAlgError:
                break
            lam = np.asarray(
                np.sqrt(np.maximum(-np.einsum("mk,mk->m", g, step), 0.0)), dtype=np.float64
            )
            bad = ~np.isfinite(lam) | ~np.isfinite(step).all(axis=1)
            step[bad] = 0.0
            lam[bad] = 0.0
            central = lam < NEAR_CENTRAL
            if central.any() or last:
                if q is not None:
                    # the multipliers 1/(s f) corrected to first order by the Newton step
                    # (f + Δf: 1/f - Δf/f²), then weights >= 0 summing to 1: a convex
                    # combination of atoms
                    df = step[:, None, 0] - np.einsum("mak,mk->ma", q, step[:, 1:])
                    fs = np.where(f > 0.0, f, 1.0)
                    p = np.where(f > 0.0, np.maximum((1.0 - df / fs) / fs, 0.0), 0.0)
                    p = p / p.sum(axis=1, keepdims=True)
                    Yn = np.einsum("ma,aij->mij", p, self.atoms_flat.reshape(-1, n, n))
                else:
                    assert Y is not None and Cis is not None
                    # (C + ΔC)⁻¹ to first order: C⁻¹ - C⁻¹ ΔC C⁻¹, ΔC = Δt I ∓ ΔM
                    dM = np.einsum("mk,mkij->mij", step[:, 1:], E)
                    for k, sign in enumerate((1.0, -1.0)):
                        dC = step[:, 0, None, None] * eye - sign * dM
                        Ck = Cis[k]
                        Y = Y - (1.0 if k == 0 else -1.0) * (Ck @ dC @ Ck)
                    Ys = 0.5 * (Y + np.swapaxes(Y, 1, 2))
                    nuc = np.abs(np.linalg.eigvalsh(Ys)).sum(axis=1)
                    Yn = Ys / nuc[:, None, None]
                lb = self.final(self.phi(Yn, M_lo, V))
                out[idx] = np.fmax(out[idx], lb)
                val = self._value(M_lo, E, x, c, q)
                if math.isinf(goal):
                    live = np.isfinite(val)
                else:
                    live = ~((lb > tau) | (val <= goal) | ~np.isfinite(val))
                if not live.any() or last:
                    break
                if not live.all():
                    keep = np.flatnonzero(live)
                    idx, x, t, s = idx[keep], x[keep], t[keep], s[keep]
                    step, lam = step[keep], lam[keep]
                    M_lo, V, E = M_lo[keep], V[keep], E[keep]
                    if c is not None and q is not None:
                        c, q = c[keep], q[keep]
            alpha = self._line_search(M_lo, E, x, t, s, step, lam, c, q)
            t = t + alpha * step[:, 0]
            x = x + alpha[:, None] * step[:, 1:]
            s = np.where(lam < NEAR_CENTRAL, s * BARRIER_RAISE, s)
        return out

    def _barrier(
        self, M_lo: Mat, E: Mat, x: Mat, t: Mat, s: Mat, c: Mat | None, q: Mat | None
    ) -> Mat:
        """``s t - Σ log det(constraints) - log det X - log det(I - X)`` (``inf`` where not
        strictly feasible)."""
        a, b, d = x[:, 0], x[:, 1], x[:, 2]
        det_x = a * d - b * b
        det_ix = (1.0 - a) * (1.0 - d) - b * b
        ok = (a > 0.0) & (d > 0.0) & (det_x > 0.0) & (a < 1.0) & (d < 1.0) & (det_ix > 0.0)
        val = s * t - np.log(np.where(ok, det_x, 1.0)) - np.log(np.where(ok, det_ix, 1.0))
        if c is not None and q is not None:
            f = t[:, None] - c - np.einsum("mak,mk->ma", q, x)
            ok &= (f > 0.0).all(axis=1)
            val -= np.log(np.where(f > 0.0, f, 1.0)).sum(axis=1)
        else:
            M = M_lo + np.einsum("mk,mkij->mij", x, E)
            # the eigenvalues of tI ∓ M are t ∓ those of M
            w = np.linalg.eigvalsh(M)
            for sign in (1.0, -1.0):
                c_w = t[:, None] - sign * w
                pos = (c_w > 0.0).all(axis=1)
                ok &= pos
                val -= np.where(pos, np.log(np.where(c_w > 0.0, c_w, 1.0)).sum(axis=1), 0.0)
        return np.where(ok & np.isfinite(val), val, np.inf)

    def _line_search(
        self,
        M_lo: Mat,
        E: Mat,
        x: Mat,
        t: Mat,
        s: Mat,
        step: Mat,
        lam: Mat,
        c: Mat | None,
        q: Mat | None,
    ) -> Mat:
        """The largest of ``1, 1/2, 1/4, 1/8`` with a strictly feasible point and Armijo's
        decrease of the barrier function, else the damped step ``1/(1 + λ)`` (always strictly
        feasible for a self-concordant barrier)."""
        alpha = 1.0 / (1.0 + lam)
        found = np.zeros(alpha.size, dtype=bool)
        f0 = self._barrier(M_lo, E, x, t, s, c, q)
        dec = -lam * lam  # the directional derivative g·step
        for a in (1.0, 0.5, 0.25, 0.125):
            f1 = self._barrier(M_lo, E, x + a * step[:, 1:], t + a * step[:, 0], s, c, q)
            take = ~found & (f1 <= f0 + 0.25 * a * dec)
            alpha = np.where(take, a, alpha)
            found |= take
            if found.all():
                break
        return alpha

    def _value(
        self, M_lo: Mat, E: Mat, x: Mat, c: Mat | None, q: Mat | None
    ) -> NDArray[np.float64]:
        """The norm of ``M(X)`` at the current ``X`` (the relaxation's primal value)."""
        if c is not None and q is not None:
            return np.asarray((c + np.einsum("mak,mk->ma", q, x)).max(axis=1), dtype=np.float64)
        M = M_lo + np.einsum("mk,mkij->mij", x, E)
        w = np.linalg.eigvalsh(M)
        return np.asarray(np.maximum(w[:, -1], -w[:, 0]), dtype=np.float64)
