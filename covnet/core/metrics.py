"""Matrix metrics ``f(A, B)`` for covariance control, and the ``METRICS`` registry.

A metric compares an achievable covariance ``A = P_i`` with a desired one ``B = P_d``.
Every metric here takes symmetric ``(..., n, n)`` arrays, broadcasts over the leading axes and
returns a ``(...)`` float64 array, so the allocator scores a whole batch of subsets in one call.
They satisfy ``f(A, B) >= 0``, ``f(A, A) = 0`` and ``f(A, B) = f(B, A)``; the triangle inequality
is not required (spec: "Matrix metrics").

To add one: write a plain function with its equation in the docstring and add one
:class:`Metric` entry to ``METRICS``; the property tests iterate over ``sorted(METRICS)``.  An
entry carries everything the rest of the system asks of a metric (its bounds, its relaxation,
whether it is batch-invariant); a metric without bounds is searched exhaustively (exact) and
refused by the searches that need a bound (the config names which).

Batch invariance.  Each function computes one matrix's value with exactly the same floating-point
operations whether it is called on one matrix or on a stack: per-matrix LAPACK calls
(``numpy.linalg`` gufuncs), elementwise ufuncs, and sums over the small last axes written out in a
fixed order (``_sum_last``) rather than left to numpy's reduction machinery, whose summation order
depends on memory layout.  The allocator relies on this: its batched search and the plain loop
over subsets then see bit-identical values, so the tie rule resolves identically.  (A user's own
metric need not be batch-invariant: the allocator then re-checks near ties one call per subset.)
"""

from __future__ import annotations

import functools
import importlib
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal, TypeVar, cast

import numpy as np
from numpy.typing import NDArray

from covnet.core import registries

MetricFn = Callable[[NDArray[np.float64], NDArray[np.float64]], NDArray[np.float64]]

#: ``np.float64`` typed as the metrics' return type.  For one ``(n, n)`` pair a metric returns a
#: float64 scalar (numpy's 0-d value, as its own reductions give), which numpy's stubs do not
#: count as an ``NDArray``; the cast is of the constructor, once, so a call costs nothing extra.
_scalar = cast("Callable[[float], NDArray[np.float64]]", np.float64)
_G = TypeVar("_G", bound=np.generic)

#: Eigenvalues within ``EIG_TIE_RTOL * max|λ|`` of each other form one tie group (svd convention).
EIG_TIE_RTOL = 1e-9


def _sum_last(x: NDArray[np.float64]) -> NDArray[np.float64]:
    """``sum_k x[..., k]`` added left to right: a fixed order whatever the layout or batch size.

    A 1-d ``x`` (one matrix's value) is added in Python floats, the same IEEE additions in the
    same order without a numpy call per term."""
    if x.ndim == 1:
        return _scalar(_left_sum(x.tolist()))
    acc = x[..., 0]
    for k in range(1, x.shape[-1]):
        acc = acc + x[..., k]
    return acc


def _left_sum(vals: list[float]) -> float:
    """``vals[0] + vals[1] + ...`` left to right (:func:`_sum_last` of one row)."""
    it = iter(vals)
    acc = next(it)
    for v in it:
        acc = acc + v
    return acc


def _max_nan(vals: list[float]) -> float:
    """``max(vals)``, NaN if any is NaN (as ``np.max``)."""
    for v in vals:
        if v != v:
            return v
    return max(vals)


def _one_pair(A: object, B: object) -> list[list[float]] | None:
    """The rows of ``A - B`` as Python floats when ``A`` and ``B`` are one ``(n, n)`` float64
    pair (``n >= 1``), else ``None``.  The metrics then do per matrix, in Python floats, the same
    IEEE operations in the same order as their batched numpy code, without a numpy call per
    step: the same bits (tested against the batched path)."""
    if (
        type(A) is np.ndarray
        and type(B) is np.ndarray
        and A.ndim == 2
        and A.shape == B.shape
        and A.size
        and A.dtype == np.float64
        and B.dtype == np.float64
    ):
        rows: list[list[float]] = (A - B).tolist()
        return rows
    return None


def _diff(A: NDArray[np.float64], B: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.asarray(A, dtype=np.float64) - np.asarray(B, dtype=np.float64)


def _diag(M: NDArray[_G]) -> NDArray[_G]:
    return np.diagonal(M, axis1=-2, axis2=-1)


# --------------------------------------------------------------------------------------------
# the metrics
# --------------------------------------------------------------------------------------------


def spectral(A: NDArray[np.float64], B: NDArray[np.float64]) -> NDArray[np.float64]:
    """Spectral norm of the difference: ``f = ||A - B||_2 = max_k |λ_k(A - B)|``.

    ``A - B`` is symmetric, so its singular values are the absolute eigenvalues.
    """
    w = np.linalg.eigvalsh(_diff(A, B))
    if w.ndim == 1 and w.size:  # one matrix: the same maximum in Python floats
        return _scalar(_max_nan([w[-1].item(), -w[0].item()]) + 0.0)
    f: NDArray[np.float64] = np.maximum(w[..., -1], -w[..., 0]) + 0.0  # -0.0 becomes 0.0
    return f


def abs_trace(A: NDArray[np.float64], B: NDArray[np.float64]) -> NDArray[np.float64]:
    """Absolute trace: ``f = sum_i |A_ii - B_ii|`` (only the diagonal of ``A - B``)."""
    rows = _one_pair(A, B)
    if rows is not None:
        return _scalar(_left_sum([abs(r[i]) for i, r in enumerate(rows)]))
    return _sum_last(np.abs(_diag(_diff(A, B))))


def ordered_eigh(
    A: NDArray[np.float64], rtol: float = EIG_TIE_RTOL
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Eigen-decomposition ``A = U diag(s) Uᵀ`` under the spec's deterministic convention.

    1. Eigenpairs are ordered by descending eigenvalue ``s``.
    2. Eigenvalues closer than ``rtol * max_k |s_k|`` (chained between neighbours) form a tie
       group.  The eigenvectors of a group are not unique, so the group's basis is rebuilt from its
       projector ``Π = U_g U_gᵀ`` alone, independent of LAPACK's choice: repeatedly take the axis
       ``a`` with the largest ``Π_aa`` (lowest index among equals), set ``u = Π e_a / sqrt(Π_aa)``
       and deflate ``Π <- Π - u uᵀ``.  ``u``'s largest-magnitude component is then ``u_a``.
    3. Within a group the vectors are ordered by the index of their largest-magnitude component;
       the group's eigenvalues stay in descending order.
    4. Each eigenvector's sign is fixed so that its largest-magnitude component is positive.

    For a diagonal matrix with repeated entries this gives the unit axes in state order within a
    tie group.  ``U[..., :, i]`` is the i-th eigenvector.  Batched over leading axes.
    """
    A = np.asarray(A, dtype=np.float64)
    if A.ndim == 2 and A.shape[0] and math.isfinite(sum(A.ravel().tolist())):
        return _ordered_eigh_one(A, rtol)
    if A.ndim == 2 and not np.any(A - np.diag(np.diagonal(A))):
        return _ordered_diagonal(np.diagonal(A).tolist(), rtol)
    w, U = np.linalg.eigh(A)
    s = w[..., ::-1]
    U = U[..., :, ::-1]
    n = s.shape[-1]
    if n > 1:
        # max|λ| = max(s_1, -s_n) for descending s
        tol = rtol * np.maximum(s[..., :1], -s[..., -1:])
        tied = (s[..., :-1] - s[..., 1:]) <= tol
        if tied.any():
            U = _canonical_rows(U, tied)
    # sign: the largest-magnitude component of every eigenvector is positive
    big = np.abs(U).argmax(axis=-2)[..., None, :]
    sign = np.where(np.take_along_axis(U, big, axis=-2) < 0.0, -1.0, 1.0)
    return s.copy(), U * sign


def _canonical_rows(U: NDArray[np.float64], tied: NDArray[np.bool_]) -> NDArray[np.float64]:
    """Step 2 of :func:`ordered_eigh` on the batched eigenvectors ``U`` ``(..., n, n)`` (columns
    in descending eigenvalue order): a copy with every tie group's columns rebuilt by
    :func:`_canonical_groups`, ``tied`` ``(..., n - 1)`` marking the neighbours that tie."""
    n = U.shape[-1]
    out = U.reshape(-1, n, n).copy()
    tied_rows = tied.reshape(-1, n - 1)
    for row in np.flatnonzero(tied_rows.any(axis=1)).tolist():
        out[row] = _canonical_groups(out[row], tied_rows[row].tolist())
    return out.reshape(U.shape)


def _ordered_eigh_one(
    A: NDArray[np.float64], rtol: float, signs: bool = True
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """:func:`ordered_eigh` of one finite ``(n, n)`` matrix: the same operations as the batched
    path, bit for bit, with the per-eigenvalue bookkeeping in Python floats instead of numpy
    calls on a few entries (all finite, so Python's ``max`` agrees with ``np.maximum``).

    ``signs=False`` skips step 4 (each eigenvector's sign): for callers that use only
    ``|u · v|``, which a column's sign does not change (negation is exact)."""
    n = A.shape[0]
    flat = A.ravel().tolist()
    off = flat.copy()
    del off[:: n + 1]
    if not any(off):  # no non-zero off-diagonal entry: A is diagonal
        return _ordered_diagonal(flat[:: n + 1], rtol)
    w, U = np.linalg.eigh(A)
    wl = w.tolist()[::-1]
    s = w[::-1]
    U = U[:, ::-1]
    if n > 1:
        tol = rtol * max(wl[0], -wl[-1])
        tied = [wl[k] - wl[k + 1] <= tol for k in range(n - 1)]
        if any(tied):
            U = _canonical_groups(U.copy(), tied)  # C order, as the batched path's copy
    if not signs:
        return s.copy(), U
    # sign: the largest-magnitude component of every eigenvector is positive
    sign = np.where(U[np.abs(U).argmax(axis=0), _arange(n)] < 0.0, -1.0, 1.0)
    return s.copy(), U * sign


@functools.lru_cache(maxsize=16)
def _arange(n: int) -> NDArray[np.intp]:
    return np.arange(n)


def _ordered_diagonal(
    d: list[float], rtol: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """:func:`ordered_eigh` of ``diag(d)`` (finite entries) without LAPACK: the same result as the
    general path (whose eigen-solver is exact on a diagonal matrix), namely the entries in
    descending order and unit axes, in state order within each tie group."""
    n = len(d)
    order = sorted(range(n), key=lambda i: (-d[i], i))
    sl = [d[i] for i in order]
    if n > 1:
        tol = rtol * max(sl[0], -sl[-1])
        start = 0
        for k in range(1, n + 1):  # sort each tie group's axes by index
            if k == n or sl[k - 1] - sl[k] > tol:
                order[start:k] = sorted(order[start:k])
                start = k
    U = np.zeros((n, n))
    U[order, np.arange(n)] = 1.0
    return np.array(sl), U


def _canonical_groups(U: NDArray[np.float64], tied: list[bool]) -> NDArray[np.float64]:
    """Replace every tie group's columns of one ``(n, n)`` eigenvector matrix (ordered_eigh).

    Plain Python floats: groups are tiny and rare, and this runs once per call for a ``P_d``
    with repeated eigenvalues."""
    n = U.shape[0]
    cols_all = U.T.tolist()  # eigenvectors as rows
    start = 0
    while start < n:
        stop = start + 1
        while stop < n and tied[stop - 1]:
            stop += 1
        if stop - start > 1:
            Ug = U[:, start:stop]
            Pi = (Ug @ Ug.T).tolist()
            chosen = []
            for _ in range(stop - start):
                d = [Pi[i][i] for i in range(n)]
                top = max(d)
                a = next(i for i in range(n) if d[i] >= top * (1.0 - 1e-9))
                root = math.sqrt(d[a])
                u = [Pi[i][a] / root for i in range(n)]
                chosen.append((a, u))
                Pi = [[Pi[i][j] - u[i] * u[j] for j in range(n)] for i in range(n)]
            chosen.sort(key=lambda au: au[0])
            cols_all[start:stop] = [u for _, u in chosen]
        start = stop
    return np.array(cols_all).T


def svd(A: NDArray[np.float64], B: NDArray[np.float64]) -> NDArray[np.float64]:
    """Orientation plus size: ``f = (n - sum_i |u_Ai · u_Bi|) / n + ||s_A - s_B||_2``.

    ``A = U_A diag(s_A) U_Aᵀ``, ``B = U_B diag(s_B) U_Bᵀ`` with eigenvalues descending and the
    eigenvector convention of :func:`ordered_eigh` (ties broken by the index of the largest
    component, that component positive).  The first term compares orientations (invariant to
    scale and eigenvector sign), the second the sizes.
    """
    A = np.asarray(A, dtype=np.float64)
    B = np.asarray(B, dtype=np.float64)
    n: int = A.shape[-1]
    if A.ndim == 2 and B.shape == A.shape and n:
        one = _svd_one(A, B, n)
        if one is not None:
            return one
    if A.ndim == 3 and B.shape == A.shape[1:] and n and A.shape[0]:
        many = _svd_stack(A, B, n)
        if many is not None:
            return many
    s_A, U_A = ordered_eigh(A)
    s_B, U_B = ordered_eigh(B)
    # cos_i = sum_k U_A[k, i] U_B[k, i], summed over k in a fixed order
    cos = _sum_last(np.swapaxes(U_A * U_B, -1, -2))
    orientation = np.maximum((n - _sum_last(np.abs(cos))) / n, 0.0)  # rounding below 0 clipped
    return orientation + np.sqrt(_sum_last((s_A - s_B) ** 2))


#: the last desired covariance's :func:`ordered_eigh` in :func:`_svd_one` and :func:`_svd_stack`
#: (a schedule changes it rarely): ``(bytes, s_B, U_B)`` as Python floats and as arrays
_SvdB = tuple[bytes, list[float], list[list[float]], NDArray[np.float64], NDArray[np.float64]]
_svd_last_B: list[_SvdB] = []


def _svd_desired(B: NDArray[np.float64]) -> _SvdB | None:
    """``B``'s :func:`ordered_eigh`, kept for the next call with the same bytes (``None`` unless
    ``B`` is finite)."""
    key = B.tobytes()
    last = _svd_last_B[0] if _svd_last_B else None
    if last is None or last[0] != key:
        if not math.isfinite(sum(B.ravel().tolist())):
            return None
        s_B, U_B = ordered_eigh(B)
        last = (key, s_B.tolist(), U_B.tolist(), s_B, U_B)
        _svd_last_B[:] = [last]
    return last


def _svd_stack(
    A: NDArray[np.float64], B: NDArray[np.float64], n: int
) -> NDArray[np.float64] | None:
    """:func:`svd` of a stack ``A`` ``(m, n, n)`` against one finite ``B`` ``(n, n)`` (``None``
    otherwise), bit for bit the general path's values with fewer steps: ``B``'s decomposition
    kept (:func:`_svd_desired`), and ``A``'s eigenvectors without :func:`ordered_eigh`'s step 4
    (each column's sign).

    Why the bits agree: a column ``i`` of ``U_A`` enters only ``cos_i = Σ_k U_A[k, i] U_B[k, i]``
    and then ``|cos_i|``.  Negating the column negates every product exactly, and the sum's
    additions (in the same fixed order, :func:`_sum_last`) then round to the negated results
    (round-to-nearest is symmetric under negation), so ``|cos_i|`` has the same bits with or
    without the sign step.  Every other operation (``np.linalg.eigh`` on the same stack, the
    descending order, the tie groups of step 2, the sums) is the general path's, in its order.
    ``tests/unit/test_metrics.py`` compares the two paths bit for bit."""
    last = _svd_desired(B)
    if last is None:
        return None
    w, U = np.linalg.eigh(A)
    s_A = w[:, ::-1]
    U_A = U[:, :, ::-1]
    if n > 1:
        tol = EIG_TIE_RTOL * np.maximum(s_A[:, :1], -s_A[:, -1:])
        tied = (s_A[:, :-1] - s_A[:, 1:]) <= tol
        if tied.any():
            U_A = _canonical_rows(U_A, tied)
    cos = _sum_last(np.swapaxes(U_A * last[4], -1, -2))
    orientation = np.maximum((n - _sum_last(np.abs(cos))) / n, 0.0)
    f: NDArray[np.float64] = orientation + np.sqrt(_sum_last((s_A - last[3]) ** 2))
    return f


def _svd_one(A: NDArray[np.float64], B: NDArray[np.float64], n: int) -> NDArray[np.float64] | None:
    """:func:`svd` of one finite ``(n, n)`` pair (``None`` otherwise): the same IEEE operations in
    the same order as the batched code (``cos_i`` summed over ``k`` ascending, then the sums of
    ``|cos_i|`` and of ``(s_A - s_B)²`` left to right), in Python floats; the eigenvectors of
    ``A`` without their sign step (``|cos_i|`` does not depend on it), ``B``'s decomposition kept
    for the next call with the same bytes."""
    flat = A.ravel().tolist()
    if not math.isfinite(sum(flat)):
        return None
    last = _svd_desired(B)
    if last is None:
        return None
    s_A, U_A = _ordered_eigh_one(A, EIG_TIE_RTOL, signs=False)
    ua, ub = U_A.tolist(), last[2]
    acc = 0.0
    for i in range(n):
        c = ua[0][i] * ub[0][i]
        for k in range(1, n):
            c = c + ua[k][i] * ub[k][i]
        acc = abs(c) if i == 0 else acc + abs(c)
    orientation = (n - acc) / n
    if orientation <= 0.0:  # np.maximum(x, 0.0): 0.0 for x <= 0 (also -0.0), NaN stays
        orientation = 0.0
    size = _left_sum([(a - b) * (a - b) for a, b in zip(s_A.tolist(), last[1], strict=True)])
    return _scalar(orientation + math.sqrt(size))


def frobenius(A: NDArray[np.float64], B: NDArray[np.float64]) -> NDArray[np.float64]:
    """Frobenius norm of the difference: ``f = ||A - B||_F = sqrt(sum_ij (A - B)_ij²)``."""
    rows = _one_pair(A, B)
    if rows is not None:
        return _scalar(math.sqrt(_left_sum([_left_sum([x * x for x in r]) for r in rows])))
    M = _diff(A, B)
    return np.sqrt(_sum_last(_sum_last(M * M)))


def one_norm(A: NDArray[np.float64], B: NDArray[np.float64]) -> NDArray[np.float64]:
    """Induced 1-norm of the difference: ``f = max_j sum_i |(A - B)_ij|`` (largest column sum)."""
    rows = _one_pair(A, B)
    if rows is not None:
        return _scalar(_max_nan([_left_sum([abs(x) for x in c]) for c in zip(*rows, strict=True)]))
    absM = np.abs(_diff(A, B))
    f: NDArray[np.float64] = np.max(_sum_last(np.swapaxes(absM, -1, -2)), axis=-1)
    return f


def inf_norm(A: NDArray[np.float64], B: NDArray[np.float64]) -> NDArray[np.float64]:
    """Induced inf-norm of the difference: ``f = max_i sum_j |(A - B)_ij|`` (largest row sum)."""
    rows = _one_pair(A, B)
    if rows is not None:
        return _scalar(_max_nan([_left_sum([abs(x) for x in r]) for r in rows]))
    f: NDArray[np.float64] = np.max(_sum_last(np.abs(_diff(A, B))), axis=-1)
    return f


def trace_diff(A: NDArray[np.float64], B: NDArray[np.float64]) -> NDArray[np.float64]:
    """Trace difference: ``f = |tr A - tr B|``.

    A pseudo-metric (``f = 0`` for any two matrices of equal trace), kept because users ask for
    it; the allocator's tie rule still makes its choice deterministic.
    """
    A = np.asarray(A, dtype=np.float64)
    B = np.asarray(B, dtype=np.float64)
    if A.ndim == 2 and A.shape == B.shape and A.size:
        d = A.shape[0] + 1
        a, b = A.ravel().tolist()[::d], B.ravel().tolist()[::d]
        return _scalar(abs(_left_sum(a) - _left_sum(b)))
    return np.abs(_sum_last(_diag(A)) - _sum_last(_diag(B)))


def _chol_logdet(A: NDArray[np.float64]) -> NDArray[np.float64]:
    """``log det A = 2 sum_i log L_ii`` with ``A = L Lᵀ``; raises ``LinAlgError`` unless SPD."""
    L = np.linalg.cholesky(A)
    return 2.0 * _sum_last(np.log(_diag(L)))


def logdet(A: NDArray[np.float64], B: NDArray[np.float64]) -> NDArray[np.float64]:
    """Symmetric log-determinant divergence (log of a determinant ratio), for SPD ``A``, ``B``:

    ``f = log det((A + B)/2) - ½ log det A - ½ log det B = log[det((A+B)/2) / sqrt(det A det B)]``.

    ``f >= 0`` with equality iff ``A = B`` (log-concavity of det); rounding below 0 is clipped.
    Log-determinants via Cholesky factors.
    """
    A = np.asarray(A, dtype=np.float64)
    B = np.asarray(B, dtype=np.float64)
    if A.ndim == 2 and B.shape == A.shape and A.size:
        # one pair: the three factorisations in one call, the sums in Python floats
        L = np.linalg.cholesky(np.array((0.5 * (A + B), A, B)))
        logs = np.log(np.diagonal(L, axis1=-2, axis2=-1)).tolist()
        ld_m, ld_a, ld_b = (2.0 * _left_sum(x) for x in logs)
        return np.maximum(_scalar(ld_m - 0.5 * (ld_a + ld_b)), 0.0)
    f = _chol_logdet(0.5 * (A + B)) - 0.5 * (_chol_logdet(A) + _chol_logdet(B))
    return np.maximum(f, 0.0)


def kl(A: NDArray[np.float64], B: NDArray[np.float64]) -> NDArray[np.float64]:
    """Symmetrised Gaussian relative entropy between ``N(0, A)`` and ``N(0, B)``, SPD inputs:

    ``f = ½[KL(A||B) + KL(B||A)] = ¼[tr(B⁻¹A) + tr(A⁻¹B) - 2n]``.

    With ``A = L_A L_Aᵀ``, ``B = L_B L_Bᵀ``: ``tr(B⁻¹A) = ||L_B⁻¹ L_A||_F²`` (triangular solves,
    no inverse).  Rounding below 0 is clipped.
    """
    A = np.asarray(A, dtype=np.float64)
    B = np.asarray(B, dtype=np.float64)
    n: int = A.shape[-1]
    if A.ndim == 2 and B.shape == A.shape and n:
        # one pair: each LAPACK step once, on a stack of 2, the sums in Python floats
        L = np.linalg.cholesky(np.array((A, B)))
        XY = np.linalg.solve(L[::-1], L)  # (L_B⁻¹ L_A, L_A⁻¹ L_B)
        tr_ba, tr_ab = (_left_sum([_left_sum(r) for r in X]) for X in (XY * XY).tolist())
        return np.maximum(_scalar(0.25 * ((tr_ba + tr_ab) - 2 * n)), 0.0)
    L_A = np.linalg.cholesky(A)
    L_B = np.linalg.cholesky(B)
    L_A, L_B = np.broadcast_arrays(L_A, L_B)
    X = np.linalg.solve(L_B, L_A)  # L_B⁻¹ L_A
    Y = np.linalg.solve(L_A, L_B)  # L_A⁻¹ L_B
    t_ba = _sum_last(_sum_last(X * X))
    t_ab = _sum_last(_sum_last(Y * Y))
    return np.maximum(0.25 * ((t_ba + t_ab) - 2 * n), 0.0)


# --------------------------------------------------------------------------------------------
# the registry: one entry per metric, carrying what the searches ask of it
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Ref:
    """A capability named by module and attribute, imported when first asked for
    (:func:`capability`): the built-in bounds need LAPACK, which a process that never decides (the
    world, a measuring sensor) must not load.  A user's entry may hold the object itself."""

    module: str
    attr: str

    def load(self) -> object:
        return getattr(importlib.import_module(self.module), self.attr)


_C = TypeVar("_C")


def capability(x: object, kind: type[_C]) -> _C | None:
    """An entry's capability (``None``, the object, or what its :class:`Ref` names), checked to
    be a ``kind`` (the bound classes live in the modules that use them, which import this one)."""
    got = x.load() if isinstance(x, Ref) else x
    if got is not None and not isinstance(got, kind):
        raise TypeError(f"expected a {kind.__name__} or None, got {type(got).__name__}")
    return got


@dataclass(frozen=True)
class Relaxation:
    """A convex relaxation of the metric over a branch-and-bound node's reduced ``2 x 2``
    information (:class:`covnet.core.allocation.search._Relaxation`, used where the gains' support
    has 2
    coordinates): ``form``, the closed form of the convex objective that module derives
    (``frobenius``: ``||·||_F²`` in ``W = Z⁻¹``; ``kl``: in ``Z``; ``logdet``: in ``W``, or in
    ``Z`` where convex there); ``leaves``: the objective is strongly convex, so the last levels
    of an exact search come from a table queried in a ball
    (:class:`covnet.core.allocation.search._Leaves`).
    """

    form: Literal["frobenius", "kl", "logdet"]
    leaves: bool = True


@dataclass(frozen=True)
class Metric:
    """``f(A, B) >= 0`` over the last two axes of batched symmetric matrices (``f(A, A) = 0``,
    ``f(A, B) = f(B, A)``), and what the searches may ask of it:

    - ``subset_bound``: a cheap lower bound of ``f`` on the fast path's approximate ``P_i``
      (:class:`covnet.core.allocation._fast.MetricBound`): prunes the batched exact search;
      without it every feasible subset is evaluated;
    - ``interval_bound``: a lower bound over a Loewner interval
      (:class:`covnet.core.allocation.interval_bounds.IntervalBound`): branch and bound; without it
      branch
      and bound is an exhaustive search, and ``search: bounded`` (or ``auto`` beyond its exact
      range) is refused by the config;
    - ``relaxation``: a convex bound over the information form (:class:`Relaxation`), tighter
      than the interval bound where it applies;
    - ``dual_bound``: the metric is a norm of ``P - P_d`` with a known dual ball
      (:class:`covnet.core.allocation.lower_bounds.DualNorm`): a weak-duality bound of the
      norm's convex relaxation over the information form, tighter than the interval bound
      where it applies;
    - ``working_floor``: a cheaper lower bound of ``f``'s computed value on a stack
      (:class:`covnet.core.allocation.svd_bound.WorkingFloor`): greedy's local search skips
      the moves it shows cannot improve (the same moves chosen, fewer evaluated);
    - ``greedy_whole_limit``: under a time limit, greedy's backward elimination and its local
      search may use the whole limit, not greedy's share of it (for a metric whose tree does
      not close the gap within the limit, so that the incumbent decides the certificate:
      :func:`covnet.core.allocation.greedy._greedy_incs_timed`);
    - ``floors_first``: with many targets under a time limit, the bounded assignment search
      runs a first round of single-target floors before deepening its enumeration (for a
      metric whose single-target search closes a target's slack in a short time:
      :mod:`covnet.core.allocation.assignment_search`, the timed plan).  Measured at N = 64,
      T = 8, 5 problems, 90 ms of CPU, against the plan without it: median gap kl 0.43 %
      (0.75 %), trace_diff 3.1 % of the distance from doing nothing (14.8 %); spectral 5.6 %
      (4.0-4.6 %), svd 4.4 % (3.4-3.6 %), the induced norms slightly worse (short floors left
      their bound weak and took the pairs' and the dual steps' time): set for the metrics with
      the reduced relaxation and trace_diff;
    - ``chain_rows``: in that timed plan, the enumeration's superset rows are split by the
      sets' first members in a fixed order of the target's sensors, each class over a
      narrower interval (:meth:`covnet.core.allocation.assignment_search._Dual.chain`).
      Measured at N = 64, T = 8, 90 ms of CPU: abs_trace 10.3 % -> 1.11 %, trace_diff 1.41 %
      -> 1.20 % of the distance from doing nothing; spectral, the induced norms and svd were
      worse with them (1.04 -> 1.34 %, 0.65 -> 3.8 %, 0.92 -> 1.29 %): set for abs_trace and
      trace_diff;
    - ``kicks``: in that timed plan, an iterated local search takes a share of the time left
      after the ejection chains (:func:`covnet.core.allocation.assignment_search._kicks`), for
      a metric whose bound settles early, so that the incumbent decides the certificate.
      Measured at N = 64, T = 8, 90 ms of CPU, over 8 seeds: abs_trace 1.11 % -> 0.48-0.92 %,
      trace_diff 0.40 % -> 0.23-0.40 %, spectral 1.03 % -> 0.89-1.12 %; one_norm's bound needs
      the time (0.65 % -> 1.13 % with them): set for spectral, abs_trace and trace_diff;
    - ``batch_invariant``: ``f`` of a stack equals ``f`` one matrix at a time, bit for bit (see
      the module docstring); otherwise the searches prune with a margin and recheck near ties.

    An entry is called like its function: ``METRICS["svd"](A, B)``."""

    name: str
    fn: MetricFn
    subset_bound: object = None  # a MetricBound, a Ref to one, or None
    interval_bound: object = None  # an IntervalBound, a Ref to one, or None
    relaxation: Relaxation | None = None
    batch_invariant: bool = False
    dual_bound: object = None  # a DualNorm, a Ref to one, or None
    working_floor: object = None  # a WorkingFloor, a Ref to one, or None
    greedy_whole_limit: bool = False
    floors_first: bool = False
    chain_rows: bool = False
    kicks: bool = False

    def __call__(self, A: NDArray[np.float64], B: NDArray[np.float64]) -> NDArray[np.float64]:
        return self.fn(A, B)


def _builtin(
    name: str,
    fn: MetricFn,
    relaxation: Relaxation | None = None,
    dual: bool = False,
    floor: Ref | None = None,
    greedy_whole_limit: bool = False,
    floors_first: bool = False,
    chain_rows: bool = False,
    kicks: bool = False,
) -> Metric:
    """A built-in metric: batch-invariant, with both bounds (named ``<NAME>_BOUND`` in
    :mod:`covnet.core.allocation._fast` and :mod:`covnet.core.allocation.interval_bounds`),
    with ``dual`` the dual bound ``<NAME>_DUAL`` of
    :mod:`covnet.core.allocation.lower_bounds`, ``floor`` its working floor,
    ``greedy_whole_limit``, ``floors_first``, ``chain_rows`` and ``kicks`` as
    :class:`Metric`'s."""
    attr = f"{name.upper()}_BOUND"
    return Metric(
        name,
        fn,
        subset_bound=Ref("covnet.core.allocation._fast", attr),
        interval_bound=Ref("covnet.core.allocation.interval_bounds", attr),
        relaxation=relaxation,
        batch_invariant=True,
        dual_bound=(
            Ref("covnet.core.allocation.lower_bounds", f"{name.upper()}_DUAL") if dual else None
        ),
        working_floor=floor,
        greedy_whole_limit=greedy_whole_limit,
        floors_first=floors_first,
        chain_rows=chain_rows,
        kicks=kicks,
    )


METRICS: dict[str, Metric] = {
    m.name: m
    for m in (
        _builtin("spectral", spectral, dual=True, kicks=True),
        _builtin("abs_trace", abs_trace, dual=True, chain_rows=True, kicks=True),
        _builtin(
            "svd",
            svd,
            floor=Ref("covnet.core.allocation.svd_bound", "SVD_FLOOR"),
            greedy_whole_limit=True,
        ),
        _builtin("frobenius", frobenius, Relaxation("frobenius"), floors_first=True),
        _builtin("one_norm", one_norm, dual=True),
        _builtin("inf_norm", inf_norm, dual=True),
        _builtin("trace_diff", trace_diff, floors_first=True, chain_rows=True, kicks=True),
        _builtin("logdet", logdet, Relaxation("logdet"), floors_first=True),
        _builtin("kl", kl, Relaxation("kl"), floors_first=True),
    )
}
registries.ship("covnet.core.metrics.METRICS", METRICS)  # what a batch's workers know


def metric_names() -> list[str]:
    """The registered metric names, sorted."""
    return sorted(METRICS)


def get_metric(name: str) -> MetricFn:
    """The function of the metric registered under ``name``; ``KeyError`` listing the valid
    names otherwise."""
    return get_entry(name).fn


def get_entry(name: str) -> Metric:
    """The entry registered under ``name``; ``KeyError`` listing the valid names otherwise."""
    try:
        return METRICS[name]
    except KeyError:
        raise KeyError(
            f"unknown metric {name!r}; valid metrics: {', '.join(metric_names())}"
        ) from None
