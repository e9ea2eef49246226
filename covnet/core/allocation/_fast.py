"""The exact fast search behind :func:`covnet.core.allocation.allocate`.

Problem (spec, "Covariance-control sensor allocation")::

    D_opt = argmin_{D_i in D_c} f(P_i, P_d),   P_i = (P⁻¹ + J_i)⁻¹,   J_i = sum_{j in D_i} J_j

with the tie rule of :func:`tie_threshold` / :func:`tie_select`.  The plain reference evaluates
``f`` exactly on every feasible subset; this module returns the same subset while evaluating
``f`` exactly on few of them.

**Gain-only tables** (:class:`SearchTables`, built once per gains and constraints, held by
:class:`covnet.core.allocation.AllocationPlan`): the feasible codes, the support, the sensors'
``S_j``, every subset's ``sum S_j`` (or the chunk tables for large ``Ns``), the subset masks and,
for small ``Ns``, every subset's exact ``J_i``.  A decision then does only ``P``-dependent work.

**Stage 1: a cheap lower bound for every feasible subset** (``2**CHUNK_BITS`` subsets at a time,
structure-of-arrays numpy, so memory stays bounded at any N).  The gains only touch the
*support* ``s`` (state coordinates with a non-zero gain entry: the positions, for position
sensors), ``r = |s|``.  With ``C = P[s, s]``, ``Kᵀ = C⁻¹ P[s, :]`` and ``P∞ = P - K P[s, :]``
(block elimination, i.e. Woodbury)::

    P_i = P∞ + K Z_i⁻¹ Kᵀ,     Z_i = C⁻¹ + S_i,     S_i = J_i[s, s] = sum_{j in D_i} S_j

so a subset costs one ``r x r`` inverse (closed form ``adj(Z) / det Z`` for the usual ``r = 2``)
and ``P_i`` is affine in it: one small matrix product per chunk.  All ``Z_i`` of a chunk come
from the per-subset sums of the sensors' ``S_j`` in the tables plus ``C⁻¹``.  The metric's
cheap bound (its entry's ``subset_bound``, :data:`covnet.core.metrics.METRICS`) runs on these
approximate ``P_i``; bounds only pay for the
entries they read (``abs_trace`` reads the diagonal).

**Small problems** (one chunk, ``r = 2 < n``: the paper's 8 sensors) are bound by the fixed cost
of numpy calls on tiny arrays, not by arithmetic, so their stage 1 is written for few calls
(:class:`_ChunkStage1P`): the plan keeps ``Q = [S_i entries; 1; det S_i]`` ``(6, B)``, in which
``Z_i``, ``det Z_i = det S_i + tr(adj(C⁻¹) S_i) + det C⁻¹``, ``adj(Z_i) - C det Z_i`` and the
numerators of the diagonal entries are all linear, so each is one ``(k, 6) @ Q`` product with
coefficients from ``C⁻¹`` and ``K`` (a few Python floats per decision).  Full matrices use
``P∞ = P - K C Kᵀ``: ``P_i = P + (K ⊗ K) vec(Z_i⁻¹ - C)``, one product with ``[K ⊗ K, vec P]``.
The diagonal bounds fold ``P∞ - P_d`` into the product (``det Z_i · (P_i - P_d)_aa``, divided
once per subset), which adds a rounding term of ``FOLD_ERR · n · eps · κ · |P∞ - P_d|`` they
deflate by.  Constants of ``P_d`` (inverse, eigen-decomposition, log-determinant) are kept per
plan for the next decisions with the same ``P_d`` (:class:`_DConstants`).

**svd** (``n = 4``, :func:`_svd_block`): the eigenvalues and the eigenvector components the
metric compares are enclosed for all subsets at once.  Every stage-1 ``P_i`` is rotated by one
orthogonal ``V`` (the eigenvectors of ``P⁻¹ + J_all/2``, folded into the stage-1 product);
the two 2 x 2 diagonal blocks of ``Vᵀ P_i V`` are solved in closed form and the coupling block
``E`` bounds the rest: eigenvalues to ``2||E||²/(η + sqrt(η² + 4||E||²))`` (Li & Li), the
eigenvectors by ``||E||/η`` out of their block and ``||E||²/(η · gap)`` within it, plus a
Davis-Kahan term for the stage-1 error; an eigenvalue without a gap above the tie tolerance is
credited nothing.  On the paper's problems this bound leaves one candidate.

**Stage 2: exact values for few subsets**, computed with the reference's arithmetic (``J_i``
summed in ascending sensor order by :func:`gain_sums`, ``P_i`` by :func:`spd_inverse`, the
metric itself on the stack).  The subset with the smallest bound is evaluated first; with ``U``
the smallest exact value so far and ``L`` the smallest bound, a subset is discarded once its
bound exceeds ``τ = U + rtol·max(|U|, |L|, tiny)``; the others are evaluated in increasing-bound
order while ``τ`` shrinks.  A metric with a ``refine`` bound (tighter, costlier: ``spectral``,
``svd``) first refines the survivors block by block, evaluating each block's best few at once so
``τ`` falls early.  As ``L <= f* <= U``, ``τ`` never drops below the reference's tie threshold
``f* + rtol·max(|f*|, tiny)``: no member of the reference's tie set is discarded, and the tie rule
runs on bit-identical values (the metrics are batch-invariant, :mod:`covnet.core.metrics`), so
the choice, its value and its ``P`` are the reference's.

**Rounding.**  A bound must stay below the exact value *as computed in floating point*.  Each
bound receives a :class:`BoundContext`: an entrywise error bound ``err`` of the stage-1 ``P_i``,
``ERR_FACTOR · n² · eps · κ · λmax(P)`` with ``κ = tr(P) tr(P⁻¹ + J_all) >= cond(P_i)`` for every
subset, and spectral limits valid for every subset by Loewner monotonicity
(``(P⁻¹ + J_all)⁻¹ <= P_i <= P``), and deflates its value by the resulting perturbation bound
plus a relative rounding allowance.  This is a worst-case error model with a generous constant,
not a certified interval computation; measured stage-1 errors stay below 1e-3 of ``err`` even
for condition numbers of 1e19 (and the property tests check bound <= exact value on every
subset).  Near-degenerate problems (the spec's scans 1-2, where subsets differ by a relative
1e-9) cannot be separated by bounds and fall back to many exact evaluations: still exact, slower.

**Fallback.**  A metric without a registered bound (a user's own function) is evaluated exactly
on every feasible subset, in batches; values within a relative 1e-6 of the tie threshold are
re-evaluated one subset per call, as the reference calls the metric.

**Why one module** (about 2000 lines, the one module of the package over 800).  The tables
(:class:`SearchTables`), a decision's setup (:class:`_Setup`, its memos, the cached ``P_d``
constants of :class:`_DConstants`), the stage-1 views (:class:`Stage1P`, :class:`_ChunkStage1P`),
the metric bounds and the two stages of :func:`fast_search` share private layouts: the
structure-of-arrays rows and the ``Q`` coefficients of a single-chunk plan, the flat index
tables, the memo keys a bound fills and reads (``setup.dc.memo["svd"]``, ``st.memo["logdet"]``,
``P.setup.det_row``).  Cut along any seam, these become an interface between two modules that
nothing else uses, and a bound's rounding argument (its deflation against the ``err`` of the
stage-1 product it reads) would span files.  The tuning constants below (``CHUNK_BITS``,
``EXACT_BLOCK``, ``SEED_POOL``) are read by the tables and by both stages, and the property
tests set them on this module.  The exact building blocks shared with the reference
(:func:`spd_inverse`, :func:`gain_sums`, :func:`tie_select`) stay with the search that must
match them bit for bit.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal, NamedTuple, TypedDict, cast

import numpy as np
from numpy.typing import NDArray

from covnet.core.gaussian import Mat
from covnet.core.lapack import flapack
from covnet.core.metrics import EIG_TIE_RTOL, MetricFn, ordered_eigh

lapack = flapack()  # scipy.linalg.lapack's routines, without scipy.linalg's import

EPS = float(np.finfo(np.float64).eps)
TINY = float(np.finfo(np.float64).tiny)
#: stage 1 processes at most 2**CHUNK_BITS subsets at a time (bounded memory at any N)
CHUNK_BITS = 12
#: a plan with a single chunk keeps every feasible subset's exact ``J_i`` when that table has at
#: most EXACT_TABLE_MAX entries (``n_feasible · n²``; 2**20 float64 = 8 MiB)
EXACT_TABLE_MAX = 2**20
#: stage 2 and the fallback evaluate at most EXACT_BLOCK subsets per batch
EXACT_BLOCK = 4096
#: with a refinable bound, the first exact evaluation goes to the best refined bound among the
#: SEED_POOL best cheap bounds, for metrics marked ``refine_seed`` or above SEED_POOL_ABOVE
#: feasible subsets
SEED_POOL = 32
#: the pool for problems of at most 1024 feasible subsets
SMALL_SEED_POOL = 128
SEED_POOL_ABOVE = 2048
#: with a refinable bound, each refined block's REFINED_PICKS best are evaluated at once
REFINED_PICKS = 4
#: the first block of refined bounds (then 4x larger each, up to EXACT_BLOCK)
REFINE_BLOCK = 16
#: stage-1 entrywise error model: err = ERR_FACTOR · n² · eps · κ · λmax(P_pred)
ERR_FACTOR = 64.0
#: an offset ``o`` folded into the products of a single-chunk plan's stage 1
#: (:meth:`_Setup.diag_coeffs`) adds at most ``FOLD_ERR · n · eps · κ · |o|`` to an entry
FOLD_ERR = 64.0


# --------------------------------------------------------------------------------------------
# exact building blocks, shared with the plain reference
# --------------------------------------------------------------------------------------------


def spd_inverse(A: NDArray[np.float64]) -> NDArray[np.float64]:
    """``A⁻¹`` of SPD ``A`` via its Cholesky factor: LAPACK ``potrf`` (``A = L Lᵀ``) then
    ``potri`` (``A⁻¹ = L⁻ᵀ L⁻¹`` from ``L``), lower triangle mirrored so the result is exactly
    symmetric.  Batched over leading axes, one LAPACK call pair per matrix: a matrix gets the same
    bits alone or in a stack.  Reads the lower triangle.  Raises ``numpy.linalg.LinAlgError``
    unless positive definite.
    """
    A = np.asarray(A, dtype=np.float64)
    if A.ndim == 2:
        return _spd_inverse_one(A)
    n = A.shape[-1]
    if A.size == n * n:
        return _spd_inverse_one(A.reshape(n, n)).reshape(A.shape)
    lo, hi = _tril(n)
    flat = A.reshape(-1, n, n)
    out = np.empty(flat.shape)
    for k in range(flat.shape[0]):
        out[k] = _potri(flat[k], k)
    out[:, hi, lo] = out[:, lo, hi]
    return out.reshape(A.shape)


def _spd_inverse_one(A: Mat) -> Mat:
    """:func:`spd_inverse` of one ``(n, n)`` float64 matrix (the same operations: ``potrf``,
    ``potri``, lower triangle copied to the upper one), with little Python overhead."""
    inv: Mat  # LAPACK on float64: float64 results (scipy-stubs type them Any)
    info: int
    c, info = _dpotrf(A, lower=1)
    if info == 0:
        inv, info = _dpotri(c, lower=1)
    if info != 0:
        raise np.linalg.LinAlgError(
            f"matrix 0 of the batch is not positive definite (LAPACK info {info})"
        )
    n = A.shape[0]
    if inv.flags.f_contiguous:  # LAPACK's usual layout: the transpose is a C-order view
        f = inv.T.reshape(n * n)
        src, dst = _mirror_flat(n)
        f[dst] = f[src]  # inv[hi, lo] = inv[lo, hi], through the transposed view
        return inv
    lo, hi = _tril(n)
    inv[hi, lo] = inv[lo, hi]
    return inv


_dpotrf, _dpotri = lapack.dpotrf, lapack.dpotri


@functools.lru_cache(maxsize=16)
def _mirror_flat(n: int) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Flat indices, in the transposed (C-order) view ``y = inv.T``, of ``y[hi, lo]`` (source:
    the lower triangle of ``inv``) and ``y[lo, hi]`` (destination: its upper triangle)."""
    lo, hi = np.tril_indices(n, -1)
    return hi * n + lo, lo * n + hi


def _potri(A: Mat, k: int) -> Mat:
    """LAPACK ``potrf`` + ``potri`` on one matrix: the inverse in the lower triangle."""
    c, info = lapack.dpotrf(A, lower=1)
    if info == 0:
        inv, info = lapack.dpotri(c, lower=1)
    if info != 0:
        raise np.linalg.LinAlgError(
            f"matrix {k} of the batch is not positive definite (LAPACK info {info})"
        )
    return np.asarray(inv)


@functools.lru_cache(maxsize=16)
def _tril(n: int) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Row and column indices of the strictly lower triangle (a constant per n)."""
    lo, hi = np.tril_indices(n, -1)
    return lo, hi


def gain_sums(gains: NDArray[np.float64], masks: NDArray[np.bool_]) -> NDArray[np.float64]:
    """``J_i = sum_{j in D_i} J_j`` for boolean rows ``masks (m, Ns)``, as ``(m, n, n)``.

    Added left to right in ascending sensor order (a cumulative sum, sequential by definition),
    so each ``J_i`` has the bits of ``J = 0; for j in subset: J = J + J_j``.  Only the members
    are added: each row's gains are gathered in ascending order and padded to the longest row
    with ``+0.0``, which changes no sum (``x + 0.0`` is ``x`` but for ``-0.0``; and a sum
    that starts from a member instead of ``+0.0`` differs from the loop's only in the sign of
    zeros while every term so far is zero).  The final ``+ 0.0`` maps ``-0.0`` to ``+0.0`` as
    the loop, which starts from ``+0.0``, would.  A row of ``k`` members costs ``k`` additions
    instead of ``Ns`` (the same bits as adding ``+0.0`` for every non-member, which it did:
    a greedy step at ``Ns = 1 000`` evaluating tied candidates paid ``Ns`` for each).
    """
    m, N = masks.shape
    n = gains.shape[-1]
    counts = masks.sum(axis=1)
    k = int(counts.max()) if m else 0
    if k == 0:
        return np.zeros((m, n, n))
    rows, cols = np.nonzero(masks)  # row-major: each row's members in ascending order
    starts = np.concatenate(([0], np.cumsum(counts)[:-1]))
    idx = np.full((m, k), N, dtype=np.intp)  # N: the zero gain appended below
    idx[rows, np.arange(rows.size) - starts[rows]] = cols
    padded = np.concatenate((gains, np.zeros((1, n, n))))
    return np.cumsum(padded[idx], axis=1)[:, -1] + 0.0


def tie_threshold(f_star: float, tie_rtol: float) -> float:
    """Values ``f <= f* + tie_rtol · max(|f*|, tiny)`` tie with the minimum ``f*``."""
    return f_star + tie_rtol * max(abs(f_star), TINY)


def tie_select(values: NDArray[np.float64], masks: NDArray[np.bool_], tie_rtol: float) -> int:
    """Row of the chosen subset: within the tie set of :func:`tie_threshold`, the fewest sensors,
    then the lexicographically smallest ascending index tuple.

    Of two subsets of equal size, the lexicographically smaller tuple is the one containing the
    lowest index at which they differ; hence the sort keys: size, then "contains sensor 0",
    "contains sensor 1", ...
    """
    thr = tie_threshold(float(values.min()), tie_rtol)
    tie = np.flatnonzero(values <= thr)
    if tie.size == 1:
        return int(tie[0])
    sub = masks[tie]
    keys = [~sub[:, j] for j in reversed(range(sub.shape[1]))] + [sub.sum(axis=1)]
    return int(tie[np.lexsort(keys)[0]])


# --------------------------------------------------------------------------------------------
# stage 1: the reduced information form, and the bounds evaluated on it
# --------------------------------------------------------------------------------------------


class BoundContext(NamedTuple):
    """What a bound may assume about the exact ``P_i`` behind its stage-1 approximation:

    - ``|P_exact - P_stage1| <= err`` entrywise;
    - ``lam_min <= λ(P_exact) <= lam_max`` (Loewner: ``(P⁻¹ + J_all)⁻¹ <= P_i <= P_pred``);
    - ``kappa >= lam_max / lam_min``, a condition-number bound valid for every subset;
    - ``scale >= max(λmax(P_pred), ||P_d||_2)``, the magnitude of the metric's inputs.
    """

    err: float
    lam_min: float
    lam_max: float
    kappa: float
    scale: float


class SearchTables:
    """Everything the search needs that depends only on the gains and the constraints, built once
    (:func:`covnet.core.allocation.prepare`); the inputs are already validated.

    - the feasible set: ``free`` sensors (bit ``b`` of a subset *code* <-> sensor ``free[b]``),
      ``req`` (always in), codes with ``kmin..kmax`` free bits, ``n_feasible`` of them;
    - the support ``s`` of the active gains (``r = |s|``), ``S_free`` ``(m, r*r)`` the free
      sensors' ``S_j = J_j[s, s]``, ``S_req`` the required ones' sum, ``active_trace`` the sum of
      the active gains' traces (for the condition-number bound of :class:`BoundContext`);
    - ``m <= CHUNK_BITS`` free sensors (*single chunk*): ``codes`` of every feasible subset,
      ``S_sub`` ``(r*r, n_feasible)`` their ``sum_{j in i, free} S_j``, ``masks`` their sensor
      rows, ``subsets`` their index tuples and, below ``EXACT_TABLE_MAX`` entries, ``J``
      ``(n_feasible, n, n)`` their ``J_i`` in the reference's arithmetic (:func:`gain_sums`), so
      an exact evaluation is one lookup plus one inverse;
    - otherwise ``S_lo`` ``(r*r, 2^c)`` / ``S_hi`` ``(r*r, 2^(m-c))`` the same sums over the low
      ``c = CHUNK_BITS`` and the high bits of a code (chunk tables, bounded memory at any N).
    """

    __slots__ = (
        "gains",
        "N",
        "n",
        "free",
        "req",
        "m",
        "kmin",
        "kmax",
        "n_feasible",
        "plain",
        "s",
        "r",
        "S_free",
        "S_req",
        "active_trace",
        "J_mid",
        "chunk",
        "codes",
        "S_sub",
        "masks",
        "subsets",
        "J",
        "S_lo",
        "pc_lo",
        "S_hi",
        "pc_hi",
        "diag_rows",
        "s_index",
        "d_cache",
        "S_req_list",
        "Q",
        "checked_d",
    )

    gains: Mat
    N: int
    n: int
    free: list[int]
    req: list[int]
    m: int
    kmin: int
    kmax: int
    n_feasible: int
    plain: bool
    s: NDArray[np.intp]
    r: int
    S_free: Mat
    S_req: Mat | None
    active_trace: float
    J_mid: Mat
    chunk: bool
    # single chunk only (else None)
    codes: NDArray[np.int64] | None
    S_sub: Mat | None
    masks: NDArray[np.bool_] | None
    subsets: list[tuple[int, ...]] | None
    J: Mat | None
    Q: Mat | None
    # several chunks only (else None)
    S_lo: Mat | None
    pc_lo: NDArray[np.int64] | None
    S_hi: Mat | None
    pc_hi: NDArray[np.int64] | None
    diag_rows: NDArray[np.intp]
    s_index: slice | NDArray[np.intp]
    d_cache: dict[bytes, _DConstants]
    S_req_list: list[float] | None
    checked_d: dict[bytes, Mat]

    def __init__(
        self, gains: Mat, excluded: frozenset[int], required: frozenset[int], max_active: int
    ) -> None:
        N, n = gains.shape[0], gains.shape[1]
        if excluded or required:
            free = [j for j in range(N) if j not in excluded and j not in required]
            req = sorted(required)
        else:
            free, req = list(range(N)), []
        m = len(free)
        self.gains, self.N, self.n, self.free, self.req, self.m = gains, N, n, free, req, m
        self.kmin = 0 if req else 1
        self.kmax = min(m, max_active - len(req))
        self.n_feasible = sum(math.comb(m, k) for k in range(self.kmin, self.kmax + 1))
        self.plain = not req and m == N  # free == all sensors, in order
        active = gains[[j for j in range(N) if j not in excluded]] if excluded else gains
        # any over axis 0 of a 2-D array is 1-D (numpy's stubs also allow a scalar)
        s = cast(NDArray[np.bool_], active.reshape(-1, n).any(axis=0)).nonzero()[0]
        r = s.size
        S = gains[:, s[:, None], s].reshape(N, r * r)
        self.s, self.r = s, r
        # a basic slice when the support is evenly spaced (the positions [0, 2] of [x, vx, y,
        # vy]): indexing P with it is a view, cheaper per decision than fancy indexing
        step = int(s[1] - s[0]) if r > 1 else 1
        even = r > 0 and step > 0 and bool(np.all(np.diff(s) == step))
        self.s_index = slice(int(s[0]), int(s[-1]) + 1, step) if even else s
        self.S_free = S if self.plain else S[free]
        self.S_req = S[req].sum(axis=0) if req else None
        self.S_req_list = self.S_req.tolist() if self.S_req is not None else None
        self.active_trace = float(np.einsum("jii->", active))
        #: half the active gains' sum: ``Y0 + J_mid`` is the reference of :func:`_svd_block`
        self.J_mid = 0.5 * active.sum(axis=0)
        self.J_mid.flags.writeable = False
        self.diag_rows = np.arange(0, n * n, n + 1)
        self.d_cache: dict[bytes, _DConstants] = {}
        #: desired covariances as given -> as checked (:func:`covnet.core.allocation.allocate`)
        self.checked_d: dict[bytes, Mat] = {}
        c = min(m, CHUNK_BITS)
        bits_lo, pc_lo = _bit_table(c)
        S_lo = self.S_free[:c].T @ bits_lo  # (r*r, 2^c)
        self.chunk = m == c
        if self.chunk:
            t = np.arange(1 << c)
            t = t[(pc_lo >= self.kmin) & (pc_lo <= self.kmax)]
            self.codes = t
            self.S_sub = np.ascontiguousarray(S_lo[:, t])
            self.masks = self.code_masks(t)
            self.subsets = [tuple(row.nonzero()[0].tolist()) for row in self.masks]
            self.J = gain_sums(gains, self.masks) if t.size * n * n <= EXACT_TABLE_MAX else None
            self.Q = None
            if r == 2:  # Z_i and det Z_i as one product (_Setup.chunk_covariances)
                Ss = self.S_sub
                self.Q = np.concatenate(
                    [Ss, np.ones((1, t.size)), (Ss[0] * Ss[3] - Ss[1] * Ss[2])[None]]
                )
            self.S_lo = self.pc_lo = self.S_hi = self.pc_hi = None
        else:
            bits_hi, pc_hi = _bit_table(m - c)
            self.S_lo, self.pc_lo = S_lo, pc_lo
            self.S_hi, self.pc_hi = self.S_free[c:].T @ bits_hi, pc_hi  # (r*r, 2^(m-c))
            self.codes = self.S_sub = self.masks = self.J = self.subsets = self.Q = None
        for a in (self.S_free, self.S_sub, self.masks, self.J, self.S_lo, self.S_hi, self.codes):
            if a is not None:
                a.flags.writeable = False

    def d_constants(self, P_d: Mat) -> _DConstants:
        """The constants of one desired covariance (:class:`_DConstants`), kept for the next
        decisions with the same ``P_d`` (a schedule changes it rarely); keyed by its bytes."""
        key = P_d.tobytes()
        dc = self.d_cache.get(key)
        if dc is None:
            if len(self.d_cache) >= D_CACHE_SIZE:
                self.d_cache.clear()
            dc = self.d_cache[key] = _DConstants(P_d)
        return dc

    def code_masks(self, codes: NDArray[np.int64]) -> NDArray[np.bool_]:
        """Boolean sensor rows ``(len(codes), N)`` of subsets given as codes."""
        bits = ((codes[:, None] >> np.arange(self.m)) & 1).astype(bool)
        if self.plain:
            return bits
        out = np.zeros((codes.shape[0], self.N), dtype=bool)
        out[:, self.free] = bits
        out[:, self.req] = True
        return out


class _DConstants:
    """Per-``P_d`` constants of the bounds, each computed on first use: ``flat`` (the entries,
    ``(n*n,)``), ``diag``, ``abs_sum`` (``sum |P_d|``), :meth:`eig` (``ordered_eigh(P_d)``),
    :meth:`inverse` (``P_d⁻¹`` and ``κ_D = tr(P_d) tr(P_d⁻¹) >= cond(P_d)``), :meth:`logdet`.
    Functions of the bits of ``P_d`` alone: one instance serves every decision with that ``P_d``."""

    __slots__ = (
        "D",
        "flat",
        "diag",
        "diag_list",
        "trace",
        "flat_list",
        "abs_sum",
        "_eig",
        "_inv",
        "_logdet",
        "memo",
    )

    def __init__(self, P_d: Mat) -> None:
        self.D = P_d.copy()
        self.D.flags.writeable = False
        self.flat = self.D.reshape(-1)
        self.diag = self.D.diagonal().copy()
        self.diag_list = self.diag.tolist()
        self.trace = float(self.D.trace())
        self.flat_list = self.flat.tolist()
        self.abs_sum = float(_sum(abs(self.D), None))
        self._eig: tuple[Mat, Mat] | None = None
        self._inv: tuple[Mat, float] | None = None
        self._logdet: float | None = None
        #: derived per-``P_d`` constants of individual bounds
        self.memo: _DMemo = {}

    def eig(self) -> tuple[Mat, Mat]:
        if self._eig is None:
            self._eig = ordered_eigh(self.D)
        return self._eig

    def inverse(self) -> tuple[Mat, float]:
        if self._inv is None:
            D_inv = spd_inverse(self.D)
            self._inv = (D_inv, self.trace * float(D_inv.trace()))
        return self._inv

    def logdet(self) -> float:
        if self._logdet is None:
            self._logdet = _logdet_spd(self.D)
        return self._logdet


#: desired covariances whose constants a plan keeps (:meth:`SearchTables.d_constants`)
D_CACHE_SIZE = 8


class _DMemo(TypedDict, total=False):
    """:attr:`_DConstants.memo`: per-``P_d`` constants of individual bounds, by key."""

    svd_blk: tuple[Mat, float, float, Mat]  # _svd_d_consts
    svd: tuple[Mat, float, NDArray[np.intp], NDArray[np.intp]]  # _svd_consts


class _SetupMemo(TypedDict, total=False):
    """:attr:`_Setup.memo`: per-decision constants of individual bounds, by key."""

    TK_P: Mat  # _Setup.TK_with
    TK_M: Mat
    gp: Mat  # _Setup.gp_coeffs
    frob_sym: tuple[Mat, float]  # _ChunkStage1P.diff_full_sym_scaled
    svd_blk: _SvdBlock  # _svd_block_consts
    svd_blk_c: _SvdBlock
    logdet: tuple[float, Mat, float, float]  # _logdet_bound
    kl: tuple[Mat, float, Mat, float]  # _kl_bound


#: a flattened ``2 x 2`` matrix in Python floats (``_Setup._base`` for ``r = 2``)
_Base4 = tuple[float, float, float, float]
#: ``_Setup._py``: ``(Kᵀ[0], Kᵀ[1], P[s0, :], P[s1, :], vec(P), a, b, c)`` with ``C⁻¹ = [[a, b],
#: [b, c]]``, Python floats (``r = 2 < n``)
_PyForm = tuple[
    list[float], list[float], list[float], list[float], list[float], float, float, float
]


class _Setup:
    """The reduced information form of one problem (module docstring).

    With ``s`` the support (``r = |s|``), ``C = P[s, s]``, ``Kᵀ = C⁻¹ P[s, :]`` and
    ``P∞ = P - K P[s, :]``: ``P_i = P∞ + K Z_i⁻¹ Kᵀ`` with ``Z_i = C⁻¹ + sum_{j in i} S_j``
    (``S_j = J_j[s, s]``).  Flattened, ``P_i = T g_i + P∞`` with ``T[(a, b), (c, d)] = K_ac K_bd``
    and ``g_i`` the entries of ``Z_i⁻¹``; for ``r = 2``, ``Z⁻¹ = adj(Z) / det Z`` with
    ``adj(Z) = J Z Jᵀ``, ``J = [[0, 1], [-1, 0]]``, so ``K`` becomes ``K J`` in ``T`` and
    ``g_i = Z_i / det Z_i``.  Only the ``P``-dependent part is built here; the gain-only part
    (support, ``S_j``, subset sums) comes from :class:`SearchTables`.
    ``memo`` holds per-problem constants of the bounds, ``dc`` those of ``P_d``.

    For ``r = 2 < n`` the constructor computes only ``C⁻¹`` and ``Kᵀ`` (Python floats); the
    arrays (``KT``, ``KJ``, ``T``, ``T_K``, ``P∞``, ...) are properties built on first use, so
    a bound pays only for what it reads.
    """

    __slots__ = (
        "n",
        "r",
        "s",
        "P",
        "Y0",
        "P_d",
        "_Zc",
        "_KT",
        "_KJ",
        "_T",
        "_T_diag",
        "_P_inf",
        "_M_inf",
        "_P_inf_diag",
        "_M_inf_diag",
        "_T_K",
        "_base",
        "_py",
        "S_free",
        "ctx",
        "memo",
        "tab",
        "dc",
    )

    n: int
    r: int
    s: NDArray[np.intp]
    P: Mat
    Y0: Mat
    P_d: Mat
    _Zc: Mat | None
    _KT: Mat | None
    _KJ: Mat | None
    _T: Mat | None
    _T_diag: Mat | None
    _P_inf: Mat | None
    _M_inf: Mat | None
    _P_inf_diag: Mat | None
    _M_inf_diag: Mat | None
    _T_K: Mat | None
    _base: _Base4 | Mat
    _py: _PyForm | None  # r = 2 < n only
    S_free: Mat
    ctx: BoundContext
    memo: _SetupMemo
    tab: SearchTables
    dc: _DConstants

    def __init__(self, P: Mat, P_d: Mat, Y0: Mat, tab: SearchTables) -> None:
        n, r, s = tab.n, tab.r, tab.s
        self.n, self.r, self.s = n, r, s
        self.P, self.Y0, self.P_d, self.tab = P, Y0, P_d, tab
        self.S_free = tab.S_free
        self.dc = dc = tab.d_constants(P_d)
        self.memo = {}
        self._T = self._T_diag = self._P_inf = self._M_inf = None
        self._P_inf_diag = self._M_inf_diag = self._KJ = self._T_K = None
        pl = P.ravel().tolist()
        self._py = None
        if r == 2 and n > 2:
            # the usual case (position sensors): C⁻¹ and Kᵀ = C⁻¹ P[s, :] in Python floats, the
            # arrays only when a bound asks for them (attributes below)
            i0, i1 = s.tolist()
            p0, p1 = pl[i0 * n : i0 * n + n], pl[i1 * n : i1 * n + n]
            c00, c01, c11 = p0[i0], p0[i1], p1[i1]
            det = c00 * c11 - c01 * c01
            a, b, c = c11 / det, -c01 / det, c00 / det
            kt0 = [a * x + b * y for x, y in zip(p0, p1, strict=True)]
            kt1 = [b * x + c * y for x, y in zip(p0, p1, strict=True)]
            self._py = (kt0, kt1, p0, p1, pl, a, b, c)
            self._Zc = self._KT = None
            sr = tab.S_req_list
            self._base = (
                (a, b, b, c) if sr is None else (a + sr[0], b + sr[1], b + sr[2], c + sr[3])
            )
        else:
            if r == n:
                KT = np.eye(n)
                P_inf = np.zeros(n * n)
                Zc = Y0
            else:
                si = tab.s_index
                Ps = P[si]
                Zc = spd_inverse(Ps[:, si]) if r else np.zeros((0, 0))
                KT = Zc @ Ps
                P_inf = (P - KT.T @ Ps).reshape(n * n)
            if r == 2:  # r = n = 2: K adj(Z) Kᵀ = (K J) Z (K J)ᵀ, J = [[0, 1], [-1, 0]]
                self._KJ = (KT[::-1] * _ADJ2_SIGN).T
            else:
                self._KJ = KT.T
            self._Zc, self._KT, self._P_inf = Zc, KT, P_inf
            base = Zc.reshape(r * r)
            self._base = base + tab.S_req if tab.S_req is not None else base
        # limits valid for every subset (a PSD matrix's trace bounds its largest eigenvalue)
        d = n + 1
        lam_max = sum(pl[::d])
        tr_Y_all = sum(Y0.diagonal().tolist()) + tab.active_trace
        kappa = lam_max * tr_Y_all
        err = ERR_FACTOR * n * n * EPS * kappa * lam_max
        self.ctx = BoundContext(err, 1.0 / tr_Y_all, lam_max, kappa, lam_max + dc.abs_sum)

    # -- the reduced form's arrays, built on first use -----------------------------------------

    @property
    def base(self) -> Mat:
        """``C⁻¹`` plus the required sensors' ``S``, flattened ``(r*r,)``."""
        if isinstance(self._base, tuple):
            self._base = np.array(self._base)
        return self._base

    @property
    def Zc(self) -> Mat:
        """``C⁻¹ = P[s, s]⁻¹`` ``(r, r)``."""
        if self._Zc is None:
            assert self._py is not None  # _Zc is computed up front unless r = 2 < n
            a, b, c = self._py[5:]
            self._Zc = np.array(((a, b), (b, c)))
        return self._Zc

    @property
    def KT(self) -> Mat:
        """``Kᵀ = C⁻¹ P[s, :]`` ``(r, n)``."""
        if self._KT is None:
            assert self._py is not None  # _KT is computed up front unless r = 2 < n
            kt0, kt1 = self._py[:2]
            self._KT = np.array((kt0, kt1))
        return self._KT

    @property
    def KJ(self) -> Mat:
        """``K`` (``K J`` for ``r = 2``, the adjugate's sign pattern folded in) ``(n, r)``."""
        if self._KJ is None:
            assert self._py is not None  # _KJ is computed up front unless r = 2 < n
            kt0, kt1 = self._py[:2]
            self._KJ = np.array([(-y, x) for x, y in zip(kt0, kt1, strict=True)])
        return self._KJ

    @property
    def P_inf(self) -> Mat:
        """``P∞ = P - K P[s, :]`` flattened ``(n*n,)``."""
        if self._P_inf is None:
            Ps = self.P[self.tab.s_index]
            self._P_inf = (self.P - self.KT.T @ Ps).reshape(self.n * self.n)
        return self._P_inf

    @property
    def M_inf(self) -> Mat:
        """``P∞ - P_d`` flattened ``(n*n,)``."""
        if self._M_inf is None:
            self._M_inf = self.P_inf - self.dc.flat
        return self._M_inf

    @property
    def T(self) -> Mat:
        """``T`` ``(n*n, r*r)``: ``P_i = T g_i + P∞`` flattened."""
        if self._T is None:
            KJ, n, r = self.KJ, self.n, self.r
            self._T = (KJ[:, None, :, None] * KJ[None, :, None, :]).reshape(n * n, r * r)
        return self._T

    @property
    def T_K(self) -> Mat:
        """``K ⊗ K`` ``(n*n, 4)`` (``r = 2 < n``): ``P_i = P + T_K vec(Z_i⁻¹ - C)`` flattened, since
        ``P∞ = P - K C Kᵀ`` (:meth:`_ChunkStage1P.full`)."""
        if self._T_K is None:
            assert self._py is not None  # r = 2 < n
            kt0, kt1 = self._py[:2]
            K = np.array((kt0, kt1)).T
            n = self.n
            self._T_K = (K[:, None, :, None] * K[None, :, None, :]).reshape(n * n, 4)
        return self._T_K

    def TK_with(self, which: Literal["P", "M"]) -> Mat:
        """``[T_K, vec(P)]`` (``which="P"``) or ``[T_K, vec(P - P_d)]`` (``"M"``) ``(n*n, 5)``:
        times ``[vec(Z_i⁻¹ - C); 1]`` (:meth:`_ChunkStage1P._gp`) they give ``P_i`` or
        ``P_i - P_d`` flattened.  Built as ``v[ia] * v[ib]`` from one vector
        ``v = [K entries, vec(P or P - P_d), 1]`` and constant index tables (:func:`_tk_index`):
        entry ``((a, b), (c, d))`` is ``K_ac K_bd``, column 4 is ``vec(·) · 1``."""
        key: Literal["TK_P", "TK_M"] = "TK_P" if which == "P" else "TK_M"
        A = self.memo.get(key)
        if A is None:
            if which == "P":
                assert self._py is not None  # r = 2 < n
                kt0, kt1, _, _, pl = self._py[:5]
                v = np.array([x for xy in zip(kt0, kt1, strict=True) for x in xy] + pl + [1.0])
            else:
                v = self.TK_vec_M()
            ia, ib = _tk_index(self.n)
            A = self.memo[key] = v[ia] * v[ib]
        return A

    def gp_coeffs(self) -> Mat:
        """``(5, 6)`` coefficients on the rows of ``Q`` (:meth:`chunk_covariances`) of
        ``[adj(Z_i) - C det Z_i; det Z_i]`` (``r = 2 < n``), i.e. of ``det Z_i · [vec(Z_i⁻¹ -
        C); 1]`` (:meth:`_ChunkStage1P._gp`)."""
        A = self.memo.get("gp")
        if A is None:
            b0, b1, b2, b3 = self._base4()
            d0, d1, d2, d3, d4, _ = self.det_row()
            assert self._py is not None  # r = 2 < n
            pl = self._py[4]
            n = self.n
            i0, i1 = self.s.tolist()
            c0, c1, c2, c3 = pl[i0 * n + i0], pl[i0 * n + i1], pl[i1 * n + i0], pl[i1 * n + i1]
            # adj(Z) = (Z11, -Z01, -Z10, Z00) with Z = b + S on Q's rows (S00, S01, S10, S11, 1,
            # det S), minus C_k times the det row (d0..d4, 1)
            # fmt: off
            A = self.memo["gp"] = np.array((
                -c0 * d0, -c0 * d1, -c0 * d2, 1.0 - c0 * d3, b3 - c0 * d4, -c0,
                -c1 * d0, -1.0 - c1 * d1, -c1 * d2, -c1 * d3, -b1 - c1 * d4, -c1,
                -c2 * d0, -c2 * d1, -1.0 - c2 * d2, -c2 * d3, -b2 - c2 * d4, -c2,
                1.0 - c3 * d0, -c3 * d1, -c3 * d2, -c3 * d3, b0 - c3 * d4, -c3,
                d0, d1, d2, d3, d4, 1.0,
            )).reshape(5, 6)
            # fmt: on
        return A

    def TK_vec_M(self) -> Mat:
        """``[K entries (row-major), vec(P - P_d), 1]`` (``r = 2 < n``): the factors of
        :meth:`TK_with` and :meth:`TK_sym_M`."""
        n = self.n
        assert self._py is not None  # r = 2 < n
        kt0, kt1 = self._py[:2]
        v = np.empty(2 * n + n * n + 1)
        v[: 2 * n : 2] = kt0
        v[1 : 2 * n : 2] = kt1
        np.subtract(self.P.reshape(n * n), self.dc.flat, out=v[2 * n : -1])
        v[-1] = 1.0
        return v

    def TK_sym_M(self) -> Mat:
        """The rows ``(a, b)``, ``a <= b``, of ``[T_K, vec(P - P_d)]`` (:meth:`TK_with`), those
        with ``a < b`` times ``sqrt 2`` ``(n(n+1)/2, 5)``."""
        ia, ib, w = _tk_sym_index(self.n)
        v = self.TK_vec_M()
        A = v[ia] * v[ib]
        A *= w
        return A

    @property
    def T_diag(self) -> Mat:
        """The diagonal rows ``T[::n+1]`` ``(n, r*r)`` alone (for bounds that read the diagonal
        only), the same products as :attr:`T`."""
        if self._T_diag is None:
            if self._T is not None:
                self._T_diag = self._T[:: self.n + 1]
            elif self._py is not None:
                kt0, kt1 = self._py[:2]
                self._T_diag = np.array(
                    [(y * y, -y * x, x * -y, x * x) for x, y in zip(kt0, kt1, strict=True)]
                )
            else:
                KJ = self.KJ
                self._T_diag = (KJ[:, :, None] * KJ[:, None, :]).reshape(self.n, self.r * self.r)
        return self._T_diag

    @property
    def P_inf_diag(self) -> Mat:
        """The diagonal of ``P∞`` ``(n,)``."""
        if self._P_inf_diag is None:
            if self._P_inf is None and self._py is not None:
                kt0, kt1, p0, p1, pl = self._py[:5]
                d = self.n + 1
                self._P_inf_diag = np.array(
                    [pl[i * d] - (kt0[i] * p0[i] + kt1[i] * p1[i]) for i in range(self.n)]
                )
            else:
                self._P_inf_diag = self.P_inf[:: self.n + 1]
        return self._P_inf_diag

    @property
    def M_inf_diag(self) -> Mat:
        """The diagonal of ``P∞ - P_d`` ``(n,)``."""
        if self._M_inf_diag is None:
            self._M_inf_diag = self.P_inf_diag - self.dc.diag
        return self._M_inf_diag

    def chunk_covariances(self) -> Stage1P:
        """Stage-1 ``P_i`` of every feasible subset of a single-chunk plan (``tab.S_sub``): a
        :class:`_ChunkStage1P` when the plan has the ``Q`` table and ``r = 2 < n``."""
        if self.tab.Q is None or self._py is None:
            assert self.tab.S_sub is not None  # a single-chunk plan
            return self.covariances(self.tab.S_sub + self.base[:, None])
        return _ChunkStage1P(self)

    def _base4(self) -> _Base4:
        b = self._base
        # r = 2: the array has four entries (tolist's length is unknown to the type system)
        return b if isinstance(b, tuple) else cast(_Base4, tuple(b.tolist()))

    def det_row(self, b: tuple[float, ...] | None = None) -> list[float]:
        """Coefficients of ``det(b + S_i)`` on the rows of ``Q`` (:meth:`chunk_covariances`),
        ``b`` the flattened ``2 x 2`` base (default ``C⁻¹`` plus the required sensors, giving
        ``det Z_i``): ``det(b + S) = det S + b3 S00 - b2 S01 - b1 S10 + b0 S11 + det b``."""
        b0, b1, b2, b3 = self._base4() if b is None else b
        return [b3, -b2, -b1, b0, b0 * b3 - b1 * b2, 1.0]

    def diag_coeffs(self, diff: bool, fold: bool) -> tuple[list[list[float]], float]:
        """Rows ``A_a`` (``a < n``) and ``A_n`` with ``A_a · Q_i = T[aa] · Z_i``, the numerator of
        ``(K Z_i⁻¹ Kᵀ)_aa = T[aa] · Z_i / det Z_i``, and ``A_n · Q_i = det Z_i``
        (:meth:`chunk_covariances`); Python floats (``r = 2 < n``).

        ``fold``: ``o_a = P∞_aa`` (``diff``: ``P∞_aa - P_d,aa``) folded in, ``A_a + o_a A_n``, so
        that ``A_a · Q_i = det Z_i · (P_i - P_d)_aa`` (no division and no addition per subset).
        Returns the rows and ``max_a |o_a|`` (the folded products round relative to it: after the
        division by ``det Z_i`` an error of a few ``eps · κ · max|o_a|``, :data:`FOLD_ERR`)."""
        assert self._py is not None  # r = 2 < n
        kt0, kt1, p0, p1, pl = self._py[:5]
        b0, b1, b2, b3 = self._base4()
        drow = self.det_row()
        d_diag = self.dc.diag_list if diff else None
        rows: list[list[float]] = []
        o_max = 0.0
        d = self.n + 1
        # K J row a = (-y, x): T[aa] = (y², -yx, -xy, x²)
        for a, (x, y) in enumerate(zip(kt0, kt1, strict=True)):
            t0, t1, t3 = y * y, -y * x, x * x
            row = [t0, t1, t1, t3, t0 * b0 + t1 * b1 + t1 * b2 + t3 * b3, 0.0]
            if fold:
                o = pl[a * d] - (x * p0[a] + y * p1[a])
                if d_diag is not None:
                    o -= d_diag[a]
                o_max = max(o_max, abs(o))
                row = [u + o * v for u, v in zip(row, drow, strict=True)]
            rows.append(row)
        rows.append(drow)
        return rows, o_max

    def covariances(self, Z: Mat) -> Stage1P:
        """Stage-1 ``P_i`` of the subsets with ``Z_i = Z[:, i]`` (``(r*r, B)``)."""
        if self.r == 2:
            det = Z[0] * Z[3] - Z[1] * Z[2]
            return Stage1P(self, Z, det, Z / det)
        return Stage1P(self, Z, None, _spd_inverse_soa(Z, self.r))

    def take(self, S1: Stage1P | None, rows: NDArray[np.intp], codes: NDArray[np.int64]) -> Stage1P:
        """Stage-1 ``P_i`` of the subsets ``codes[rows]``, where ``S1`` holds all of ``codes``
        (``None`` for a plan of several chunks): the same representation restricted to those
        columns for a single-chunk :class:`_ChunkStage1P`, else :meth:`subsets`."""
        if isinstance(S1, _ChunkStage1P):
            return S1.take(rows)
        return self.subsets(codes[rows])

    def subsets(self, codes: NDArray[np.int64]) -> Stage1P:
        """Stage-1 ``P_i`` of arbitrary subsets (codes over the free sensors)."""
        bits = ((codes[None, :] >> np.arange(self.S_free.shape[0])[:, None]) & 1).astype(float)
        return self.covariances(self.base[:, None] + self.S_free.T @ bits)


# the ufuncs' reduce methods, typed for the float64 arrays they get here (the stubs say Any)
_sum: Callable[..., Mat] = np.add.reduce
_max: Callable[..., Mat] = np.maximum.reduce


@functools.lru_cache(maxsize=16)
def _tk_index(n: int) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Index tables of :meth:`_Setup.TK_with` for ``v = [K (n x 2) row-major, vec (n*n), 1]``."""
    ab = np.arange(n * n)
    a, b = ab // n, ab % n
    ia = np.empty((n * n, 5), dtype=np.intp)
    ib = np.empty((n * n, 5), dtype=np.intp)
    for cd, (c, d) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
        ia[:, cd] = 2 * a + c
        ib[:, cd] = 2 * b + d
    ia[:, 4] = 2 * n + ab
    ib[:, 4] = 2 * n + n * n
    ia.flags.writeable = ib.flags.writeable = False
    return ia, ib


@functools.lru_cache(maxsize=16)
def _tk_sym_index(n: int) -> tuple[NDArray[np.intp], NDArray[np.intp], Mat]:
    """The rows ``(a, b)``, ``a <= b``, of :func:`_tk_index`, and their weights ``(k, 1)``: ``1``
    on the diagonal, ``sqrt 2`` off it."""
    ia, ib = _tk_index(n)
    a, b = np.triu_indices(n)
    rows = a * n + b
    w = np.where(a == b, 1.0, math.sqrt(2.0))[:, None]
    out = ia[rows], ib[rows], w
    for x in out:
        x.flags.writeable = False
    return out


_min: Callable[..., Mat] = np.minimum.reduce
_ADJ2_SIGN = np.array([[-1.0], [1.0]])  # Jᵀ Kᵀ = [-Kᵀ[1], Kᵀ[0]]


class Stage1P:
    """The stage-1 covariances of ``B`` subsets, structure-of-arrays: entry ``(i, j)`` of every
    subset's ``P_i`` is one ``(B,)`` row, computed on demand (a bound that needs only the
    diagonal pays only for it).

    ``diag()`` ``(n, B)``, ``full()`` ``(n*n, B)`` (row ``i*n + j``), ``stack()`` ``(B, n, n)``;
    ``diff_diag()``, ``diff_full()``, ``diff_stack()`` the same for ``P_i - P_d``.
    ``Z`` ``(r*r, B)``: the subsets' information on the support, ``det`` its determinant when
    ``r = 2``; ``setup`` the problem's :class:`_Setup`.
    """

    __slots__ = ("n", "size", "setup", "Z", "det", "_g", "_full")

    n: int
    size: int
    setup: _Setup
    Z: Mat
    det: Mat | None  # r = 2 only
    _g: Mat
    _full: Mat | None

    def __init__(self, setup: _Setup, Z: Mat, det: Mat | None, g: Mat) -> None:
        self.n, self.size, self.setup = setup.n, Z.shape[1], setup
        self.Z, self.det, self._g = Z, det, g
        self._full = None

    def diag(self) -> Mat:
        X = self.setup.T_diag @ self._g
        X += self.setup.P_inf_diag[:, None]
        return X

    def diff_diag(self) -> Mat:
        X = self.setup.T_diag @ self._g
        X += self.setup.M_inf_diag[:, None]
        return X

    def full(self) -> Mat:
        if self._full is None:
            X = self.setup.T @ self._g
            X += self.setup.P_inf[:, None]
            self._full = X
        return self._full

    def diff_full(self) -> Mat:
        X = self.setup.T @ self._g
        X += self.setup.M_inf[:, None]
        return X

    def stack(self) -> Mat:
        return self.full().reshape(self.n, self.n, self.size).transpose(2, 0, 1)

    def diff_stack(self) -> Mat:
        return self.diff_full().reshape(self.n, self.n, self.size).transpose(2, 0, 1)


class _ChunkStage1P(Stage1P):
    """:class:`Stage1P` of all subsets of a single-chunk plan with ``r = 2 < n``, from the plan's
    ``Q = [S_i entries; 1; det S_i]`` rows ``(6, B)``: ``Z_i``, ``det Z_i`` and the diagonal
    entries' numerators are linear in them, so each is one small product ``A @ Q`` (coefficients
    ``A`` from ``C⁻¹`` and ``K``) instead of one numpy call per term.  ``Z``, ``det`` and the
    entries of ``Z_i⁻¹`` are computed on first use (a diagonal-only bound never needs them)."""

    __slots__ = ("Q", "_Zd", "_g_lazy", "_gp_lazy")

    Q: Mat

    def __init__(self, setup: _Setup, rows: NDArray[np.intp] | None = None) -> None:
        Q = setup.tab.Q
        assert Q is not None  # built only for plans with the Q table (chunk_covariances)
        self.Q = Q if rows is None else Q[:, rows]
        self.n, self.size, self.setup = setup.n, self.Q.shape[1], setup
        self._Zd: Mat | None = None
        self._g_lazy: Mat | None = None
        self._gp_lazy: Mat | None = None
        self._full = None

    def take(self, rows: NDArray[np.intp]) -> _ChunkStage1P:
        """The same subsets' stage 1 restricted to the columns ``rows``; what is already computed
        is sliced, not recomputed."""
        sub = _ChunkStage1P(self.setup, rows)
        for name in ("_Zd", "_g_lazy", "_gp_lazy"):
            X = getattr(self, name)
            if X is not None:
                setattr(sub, name, X[:, rows])
        return sub

    def _zd(self) -> Mat:
        if self._Zd is None:
            b0, b1, b2, b3 = self.setup._base4()
            B = np.array(
                [1.0, 0.0, 0.0, 0.0, b0, 0.0, 0.0, 1.0, 0.0, 0.0, b1, 0.0]
                + [0.0, 0.0, 1.0, 0.0, b2, 0.0, 0.0, 0.0, 0.0, 1.0, b3, 0.0]
                + self.setup.det_row()
            ).reshape(5, 6)
            self._Zd = B @ self.Q
        return self._Zd

    @property
    def Z(self) -> Mat:  # type: ignore[override]
        return self._zd()[:4]

    @property
    def det(self) -> Mat:  # type: ignore[override]
        d: Mat = self._zd()[4]
        return d

    @property
    def _g(self) -> Mat:  # type: ignore[override]
        if self._g_lazy is None:
            Zd = self._zd()
            self._g_lazy = Zd[:4] / Zd[4]
        return self._g_lazy

    def _gp(self) -> Mat:
        """``[vec(Z_i⁻¹ - C); 1]`` ``(5, B)``, ``C = P[s, s]``: ``adj(Z_i) - C det Z_i`` and
        ``det Z_i`` are linear in the rows of ``Q`` (one product), then one division; the last
        row of ones carries the constant term of :meth:`full` / :meth:`diff_full` (one product
        with ``[T_K, vec(P)]``, no addition per subset)."""
        if self._gp_lazy is None:
            R = self.setup.gp_coeffs() @ self.Q
            R[:4] /= R[4]
            R[4] = 1.0
            self._gp_lazy = R
        return self._gp_lazy

    def diff_full_sym_scaled(self) -> tuple[Mat, float]:
        """``R`` with rows ``w_ab · det Z_i · (P_i - P_d)_ab`` for ``a <= b`` (``w = 1`` on the
        diagonal, ``sqrt 2`` off it, so the squares of the rows sum to ``det Z_i² ||P_i -
        P_d||_F²``) and a last row ``det Z_i``, in one product with ``Q``: ``det Z_i · [vec(Z_i⁻¹
        - C); 1]`` is linear in ``Q`` (:meth:`_Setup.gp_coeffs`), so the coefficients are
        ``[T_K, vec(P - P_d)]`` (symmetric rows) times those of :meth:`_gp`; and the absolute
        error bound the folding adds to each entry of ``P_i - P_d`` (relative to ``|P - P_d|``
        and ``|K C Kᵀ| <= λmax``, as :meth:`_Setup.diag_coeffs`)."""
        st = self.setup
        c = st.memo.get("frob_sym")
        if c is None:
            A = st.gp_coeffs()
            TKs = st.TK_sym_M()
            k = TKs.shape[0]
            C = np.empty((k + 1, 6))
            np.matmul(TKs, A, out=C[:k])
            C[k] = A[4]
            # |P - P_d| <= λmax + sum|P_d| = scale entrywise
            o_max = st.ctx.scale + st.ctx.lam_max
            c = st.memo["frob_sym"] = (C, FOLD_ERR * self.n * EPS * st.ctx.kappa * o_max)
        C, fold = c
        return C @ self.Q, fold

    def full(self) -> Mat:
        if self._full is None:
            self._full = self.setup.TK_with("P") @ self._gp()
        return self._full

    def diff_full(self) -> Mat:
        return self.setup.TK_with("M") @ self._gp()

    def _diag_rows(self, offset: Mat) -> Mat:
        rows, _ = self.setup.diag_coeffs(False, False)
        R = np.array(rows) @ self.Q
        n = self.n
        X = R[:n]
        X /= R[n]
        X += offset[:, None]
        return X

    def diff_diag_scaled(self, total: bool = False) -> tuple[Mat, float]:
        """``R`` with ``R[a] = det Z_i · (P_i - P_d)_aa`` (``a < n``; ``total``: one row, their
        sum) and last row ``det Z_i``, in one product; and the absolute error bound that the
        folding adds to each ``(P_i - P_d)_aa`` (:meth:`_Setup.diag_coeffs`)."""
        st = self.setup
        rows, o_max = st.diag_coeffs(True, True)
        if total:
            rows = [[sum(c) for c in zip(*rows[:-1], strict=True)], rows[-1]]
        return np.array(rows) @ self.Q, FOLD_ERR * self.n * EPS * st.ctx.kappa * o_max

    def diag(self) -> Mat:
        return self._diag_rows(self.setup.P_inf_diag)

    def diff_diag(self) -> Mat:
        return self._diag_rows(self.setup.M_inf_diag)


BoundFn = Callable[[Stage1P, NDArray[np.float64], BoundContext], NDArray[np.float64]]


@dataclass(frozen=True, slots=True)
class MetricBound:
    """Lower bounds for one metric: ``cheap`` runs on every feasible subset, the optional
    ``refine`` (tighter, costlier) only on the survivors of ``cheap``.

    Contract: ``fn(P, P_d, ctx)`` returns ``(P.size,)`` values ``<= metric(P_exact, P_d)`` *as
    computed in floating point*, for every ``P_exact`` allowed by ``ctx``.  NaN or ``-inf``
    (no information) are always safe.
    """

    cheap: BoundFn
    refine: BoundFn | None = None
    #: refine a pool of the best cheap bounds before the first exact evaluation even for small
    #: problems (worth it when ``cheap`` is loose, as the size-only bound of ``svd`` for
    #: ``n != 4`` is); a function of the state dimension ``n`` or a constant
    refine_seed: bool | Callable[[int], bool] = False


def _cov_slack(v: Mat, lipschitz: float, ctx: BoundContext, extra: float = 0.0) -> Mat:
    """Deflate a value ``v >= 0`` in covariance units that moves by at most ``lipschitz · err``
    when ``P`` moves by ``err`` entrywise; plus a relative ``64 n eps`` (of ``v`` and of the input
    scale) for the rounding of both computations, and ``extra`` (an absolute error of ``v``
    known to the caller)."""
    rel = 64.0 * lipschitz * EPS
    v *= 1.0 - rel  # in place: every caller passes a fresh array
    v -= lipschitz * ctx.err + rel * ctx.scale + extra
    return v


def _abs_trace_bound(P: Stage1P, D: Mat, ctx: BoundContext) -> Mat:
    """``sum_i |(P - D)_ii|`` of the stage-1 ``P``."""
    if isinstance(P, _ChunkStage1P):  # sum_i |det Z · (P - D)_ii| / det Z
        R, fold = P.diff_diag_scaled()
        X = R[: P.n]
        v = _sum(np.abs(X, out=X), 0)
        v /= R[P.n]
        return _cov_slack(v, P.n, ctx, P.n * fold)
    X = P.diff_diag()
    return _cov_slack(_sum(np.abs(X, out=X), 0), P.n, ctx)


def _trace_diff_bound(P: Stage1P, D: Mat, ctx: BoundContext) -> Mat:
    """``|tr(P - D)|`` of the stage-1 ``P``."""
    if isinstance(P, _ChunkStage1P):  # |det Z · tr(P - D)| / det Z
        R, fold = P.diff_diag_scaled(total=True)
        v = np.abs(R[0], out=R[0])
        v /= R[1]
        return _cov_slack(v, P.n, ctx, P.n * fold)
    return _cov_slack(np.abs(_sum(P.diff_diag(), 0)), P.n, ctx)


def _frobenius_bound(P: Stage1P, D: Mat, ctx: BoundContext) -> Mat:
    """``||P - D||_F`` of the stage-1 ``P``."""
    if isinstance(P, _ChunkStage1P):  # sqrt(sum_(a<=b) (w_ab det Z (P - D)_ab)²) / det Z
        R, fold = P.diff_full_sym_scaled()
        k = R.shape[0] - 1
        X = R[:k]
        X *= X
        v = _sum(X, 0)
        np.sqrt(v, out=v)
        v /= R[k]
        return _cov_slack(v, P.n, ctx, P.n * fold)
    M = P.diff_full()
    return _cov_slack(np.sqrt(np.einsum("kb,kb->b", M, M)), P.n, ctx)


def _one_norm_bound(P: Stage1P, D: Mat, ctx: BoundContext) -> Mat:
    """``max_j sum_i |(P - D)_ij|`` of the stage-1 ``P``."""
    return _cov_slack(_max(_sum_mats(P.n)[0] @ np.abs(P.diff_full()), 0), P.n, ctx)


def _inf_norm_bound(P: Stage1P, D: Mat, ctx: BoundContext) -> Mat:
    """``max_i sum_j |(P - D)_ij|`` of the stage-1 ``P``."""
    return _cov_slack(_max(_sum_mats(P.n)[1] @ np.abs(P.diff_full()), 0), P.n, ctx)


def _spectral_cheap(P: Stage1P, D: Mat, ctx: BoundContext) -> Mat:
    """``||M||_2`` is at least the largest column norm ``max_j ||M e_j||_2`` and, by Cauchy
    interlacing, the spectral norm of any 2 x 2 principal submatrix, ``|m| + sqrt(h² + o²)`` with
    ``m`` (``h``) the mean (half difference) of its diagonal and ``o`` its off-diagonal entry."""
    n = P.n
    M = P.diff_full()
    lb = _max(_sum_mats(n)[0] @ (M * M), 0)  # squared column norms
    np.sqrt(lb, out=lb)
    if n > 1:
        ii, jj, ij = _pair_rows(n)
        dj = M[jj]
        half = M[ii]
        half -= dj
        half *= 0.5
        off = M[ij]
        off *= off
        dj += half
        np.abs(dj, out=dj)
        half *= half
        half += off
        np.sqrt(half, out=half)
        half += dj
        np.maximum(lb, _max(half, 0), out=lb)
    return _cov_slack(lb, n, ctx)


@functools.lru_cache(maxsize=16)
def _pair_rows(n: int) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp]]:
    """For the flattened ``(n*n, B)`` layout: the rows of ``M_ii``, ``M_jj``, ``M_ij`` for the
    index pairs ``i < j`` (constants per n)."""
    pi, pj = np.triu_indices(n, 1)
    return pi * (n + 1), pj * (n + 1), pi * n + pj


@functools.lru_cache(maxsize=16)
def _sum_mats(n: int) -> tuple[Mat, Mat]:
    """``(n, n*n)`` 0/1 matrices summing the flattened ``(n*n, B)`` layout over ``i`` for each
    column ``j`` and over ``j`` for each row ``i`` (constants per n)."""
    col = np.zeros((n, n * n))
    row = np.zeros((n, n * n))
    for j in range(n):
        col[j, j::n] = 1.0
        row[j, j * n : j * n + n] = 1.0
    col.flags.writeable = row.flags.writeable = False
    return col, row


@functools.lru_cache(maxsize=16)
def _pairs(n: int) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Index pairs ``i < j`` (a constant per n)."""
    pi, pj = np.triu_indices(n, 1)
    return pi, pj


def _spectral_refine(P: Stage1P, D: Mat, ctx: BoundContext) -> Mat:
    """The spectral norm of the stage-1 ``M`` (Weyl: it moves by ``<= ||ΔP||_2 <= n err``)."""
    w = np.linalg.eigvalsh(P.diff_stack())
    return _cov_slack(np.maximum(w[:, -1], -w[:, 0]), P.n, ctx)


def _svd_cheap(P: Stage1P, D: Mat, ctx: BoundContext) -> Mat:
    """The cheap ``svd`` bound: :func:`_svd_block` (size and orientation) for ``n = 4``, else
    :func:`_svd_size_cheap` (size only)."""
    if P.n == 4:
        return _svd_block(P, D, ctx)
    return _svd_size_cheap(P, D, ctx)


def _svd_size_cheap(P: Stage1P, D: Mat, ctx: BoundContext) -> Mat:
    """Size term only (the orientation term is ``>= 0``).  With ``λ`` the eigenvalues of ``P``
    and ``s`` those of ``D``, both descending, ``||λ - s||_2`` is at least

    - ``|tr P - tr D| / sqrt(n)`` (Cauchy-Schwarz on ``sum_i (λ_i - s_i)``);
    - ``(tr P - min_i P_ii - sum_{i<n} s_i) / sqrt(n-1)`` and
      ``(sum_{i>1} s_i - tr P + max_i P_ii) / sqrt(n-1)``: by Ky Fan (Schur-Horn) the ``n-1``
      largest (smallest) eigenvalues sum to at least (at most) the ``n-1`` largest (smallest)
      diagonal entries;
    - ``sqrt(sum_i d_i²)`` with ``d_i`` the distance from ``s_i`` to the interval that Cauchy
      interlacing gives for ``λ_i`` from the 2 x 2 principal submatrices (eigenvalues
      ``μ_1 >= μ_2``): ``λ_1 >= max μ_1``, ``λ_2 >= max μ_2``, ``λ_{n-1} <= min μ_1``,
      ``λ_n <= min μ_2``.
    """
    n = P.n
    s_D, sum_D, pi, pj = _svd_consts(P.setup, D)
    A = P.full()
    diag = A[:: n + 1]
    tr = diag.sum(axis=0)
    lb = np.abs(tr - sum_D) / math.sqrt(n)
    if n > 1:
        r = 1.0 / math.sqrt(n - 1)
        lb = np.maximum(lb, (tr - diag.min(axis=0) - (sum_D - s_D[-1])) * r)
        lb = np.maximum(lb, ((sum_D - s_D[0]) - tr + diag.max(axis=0)) * r)
        half = 0.5 * (diag[pi] - diag[pj])
        off = A[pi * n + pj]
        rad = np.sqrt(half * half + off * off)
        mid = diag[pj] + half  # (d_i + d_j) / 2
        mu1, mu2 = mid + rad, mid - rad
        lower = [mu1.max(axis=0), mu2.max(axis=0)]  # for λ_1, λ_2
        upper = [mu1.min(axis=0), mu2.min(axis=0)]  # for λ_{n-1}, λ_n
        dist = [np.maximum(lower[0] - s_D[0], 0.0), np.maximum(lower[1] - s_D[1], 0.0)]
        if n == 2:
            pass  # the only 2 x 2 block is P: its eigenvalues are λ itself, lower bounds suffice
        elif n == 3:  # λ_2 has both bounds
            dist[1] = np.maximum(dist[1], s_D[1] - upper[0])
            dist.append(np.maximum(s_D[2] - upper[1], 0.0))
        else:
            dist.append(np.maximum(s_D[n - 2] - upper[0], 0.0))
            dist.append(np.maximum(s_D[n - 1] - upper[1], 0.0))
        lb = np.maximum(lb, np.sqrt(sum(x * x for x in dist)))
    # each μ moves by <= 2 err, the Ky Fan terms by <= (n + 1) err / sqrt(n - 1): 2n covers all
    return _cov_slack(lb, 2.0 * n, ctx)


_dsyev = lapack.dsyev


def _svd_rows() -> Mat:
    """``(11, 16)``: the rows ``m_A, m_C, h_A, h_C, b_A, b_C, m_A - m_C, 2E`` of
    :func:`_svd_block` as combinations of the 16 entries ``M_ij`` (index ``4i + j``)."""
    G = np.zeros((11, 16))
    G[0, 0] = G[0, 5] = G[2, 0] = G[1, 10] = G[1, 15] = G[3, 10] = 0.5
    G[2, 5] = G[3, 15] = -0.5
    G[4, 1] = G[5, 11] = 1.0
    G[6] = G[0] - G[1]
    for k, ij in enumerate((2, 3, 6, 7)):  # E = M[:2, 2:]
        G[7 + k, ij] = 2.0
    G.flags.writeable = False
    return G


_SVD_ROWS = _svd_rows()
_EYE4 = np.eye(4)
_EYE4.flags.writeable = False


class _SvdBlock(NamedTuple):
    """Per-decision constants of :func:`_svd_block`: the 15 rows as coefficients on the stage-1
    representation (``coef``; plus ``const`` for a general :class:`Stage1P`), ``s_D``'s half
    gaps ``d``, ``½||w_j||²`` of its own block and ``½||w_j||`` of the other one, the error
    bounds ``c`` (``>= 2e`` plus the size's rounding) and ``δ``, the tie threshold ``tie``
    (``>= e``) and the relative rounding of the size."""

    coef: Mat
    const: Mat | None
    d: Mat
    half_n2: Mat
    n_other: Mat
    c: float
    delta: float
    tie: float
    rel: float


def _svd_d_consts(dc: _DConstants) -> tuple[Mat, float, float, Mat]:
    """``(U_D, σ_A, σ_C, [[d_A], [d_C]])`` of one ``P_d`` (cached with it): ``s_D = (σ_A ± d_A,
    σ_C ± d_C)`` descending, ``U_D`` the eigenvectors of
    :func:`covnet.core.metrics.ordered_eigh`."""
    k = dc.memo.get("svd_blk")
    if k is None:
        s_D, U_D = dc.eig()
        s = s_D.tolist()
        d = np.array([[0.5 * (s[0] - s[1])], [0.5 * (s[2] - s[3])]])
        k = dc.memo["svd_blk"] = (U_D, 0.5 * (s[0] + s[1]), 0.5 * (s[2] + s[3]), d)
    return k


def _svd_block_consts(P: Stage1P) -> _SvdBlock:
    """The constants of :func:`_svd_block` for one decision (kept in ``setup.memo``)."""
    st = P.setup
    chunk = isinstance(P, _ChunkStage1P)
    key: Literal["svd_blk_c", "svd_blk"] = "svd_blk_c" if chunk else "svd_blk"
    k = st.memo.get(key)
    if k is not None:
        return k
    n, ctx = 4, st.ctx
    # V: eigenvectors of the reference Y0 + J_mid (the information of half of every active
    # gain), ascending information = descending covariance.  Any V is valid; this one makes
    # the coupling E small for every subset of the paper's problems.
    _, V, info = _dsyev(st.Y0 + st.tab.J_mid)
    if info != 0:
        V = _EYE4
    U_D, sA, sC, d = _svd_d_consts(st.dc)
    if chunk:  # P_i = P + (K ⊗ K) vec(Z_i⁻¹ - C): coefficients on [vec(Z_i⁻¹ - C); 1]
        Kc, base = st.KT, st.P
    else:  # P_i = P∞ + (KJ ⊗ KJ) g_i
        Kc, base = st.KJ.T, st.P_inf.reshape(n, n)
    # Vᵀ [V, U_D, base V, Kcᵀ]: VᵀV, w_j = Vᵀ u_Dj, Vᵀ base V, Uᵀ = (Kc V)ᵀ
    X = V.T @ np.concatenate((V, U_D, base @ V, Kc.T), axis=1)
    xl = X.tolist()
    delta = 16.0 * n * EPS  # >= ||V - Q||_2 (<= ||VᵀV - I||_2 <= Σ|VᵀV - I|)
    for i, row in enumerate(xl):
        for j in range(n):
            delta += abs(row[j] - 1.0) if i == j else abs(row[j])
    Ut = X[:, 3 * n :]  # (4, r): M_ij = sum_cd U_ci U_dj g_cd (+ Vᵀ base V)
    r2 = Ut.shape[1] * Ut.shape[1]
    O = np.empty((n * n, r2 + 1))
    O[:, :r2] = (Ut[:, None, :, None] * Ut[None, :, None, :]).reshape(n * n, r2)
    O[:, r2] = X[:, 2 * n : 3 * n].reshape(n * n)
    C11 = _SVD_ROWS @ O  # (11, r² + 1)
    # t_j = ±½ (p_j h + q_j b) on j's block, p = w_0² - w_1², q = 2 w_0 w_1 (w = w_j's block)
    mix = [0.0] * 16
    g, h2, n_oth = [], [], []
    for j, i0 in enumerate((0, 0, 2, 2)):
        w0, w1 = xl[i0][n + j], xl[i0 + 1][n + j]
        o0, o1 = xl[2 - i0][n + j], xl[3 - i0][n + j]
        p, q = w0 * w0 - w1 * w1, 2.0 * w0 * w1
        half = 0.5 if j % 2 == 0 else -0.5  # the block's larger / smaller eigenvalue
        b = i0 // 2  # rows h, b of the block: C11[2 + b], C11[4 + b] (mix columns b, 2 + b)
        mix[4 * j + b] = half * p
        mix[4 * j + 2 + b] = half * q
        g.append(0.5 * (abs(p) + abs(q)))
        h2.append(0.5 * (w0 * w0 + w1 * w1) + 64.0 * EPS)
        n_oth.append(0.5 * math.sqrt(o0 * o0 + o1 * o1))
    coef = np.empty((15, r2 + 1))
    coef[:11] = C11
    np.matmul(np.array(mix).reshape(4, 4), C11[2:6], out=coef[11:])
    # e >= ||M̃ - Qᵀ P_exact Q||_2 (docstring of _svd_block)
    v1 = (1.0 + delta) ** 2
    e = 2.0 * n * n * v1 * ctx.err + 3.0 * delta * ctx.lam_max + 64.0 * n * EPS * v1 * ctx.scale
    rnd = 32.0 * EPS * v1 * ctx.scale
    shift = np.array([-sA, -sC, 0.0, 0.0, 0.0, 0.0, -rnd, 0.0, 0.0, 0.0, 0.0] + g)
    shift[11:] *= e
    const = None
    if chunk:
        coef[:, r2] += shift
    else:
        const = coef[:, r2] + shift
        coef = coef[:, :r2]
    hn = np.array(h2 + n_oth).reshape(2, 2, 2, 1)
    k = _SvdBlock(
        coef,
        const,
        d,
        hn[0],
        hn[1],
        2.0 * e + 2.0 * rnd + 128.0 * n * EPS * ctx.scale + 2.0 * n * ctx.err,
        2.0 * delta + 64.0 * n * EPS,
        EIG_TIE_RTOL * (ctx.lam_max + e) + e,
        128.0 * n * EPS,
    )
    st.memo[key] = k
    return k


def _svd_block(P: Stage1P, D: Mat, ctx: BoundContext) -> Mat:
    """Size plus orientation from a 2 + 2 block split (``n = 4``), every subset at once.

    **Rotation.**  ``V``: the eigenvectors of one reference ``Y0 + J_mid`` (half of every
    active gain), columns by descending covariance; ``Q`` the orthogonal polar factor of ``V``,
    ``δ = Σ|VᵀV - I| >= ||V - Q||_2``.  ``M = Vᵀ P_i V = [[A, E], [Eᵀ, C]]`` (2 x 2 blocks): its
    rows ``m_A - σ_A``, ``h_A``, ``b_A`` (``A = [[m_A + h_A, b_A], [b_A, m_A - h_A]]``), the same
    for ``C``, ``m_A - m_C``, ``2E`` and the ``t_j`` below come from one product of per-decision
    coefficients (``V`` folded into the stage-1 representation) with the subsets' columns.  With
    ``M̃`` the matrix the computed rows define, ``||M̃ - Qᵀ P_exact Q||_2 <= e = 2n²(1+δ)² err
    + 3δ λmax + 64 n eps (1+δ)² scale`` (stage-1 error through the fold, ``V`` versus ``Q``,
    rounding, and LAPACK's backward error for the eigenpairs the metric computes).

    **Eigenvalues.**  ``A`` has ``a_{1,2} = m_A ± r_A``, ``r_A = sqrt(h_A² + b_A²)``, ``C`` has
    ``c_{1,2} = m_C ± r_C``.  If ``η = a_2 - c_1 > 0`` the sorted eigenvalues of
    ``diag(A, C)`` are ``λ̂ = (a_1, a_2, c_1, c_2)`` and (Li & Li 2005, quadratic residual bound)
    ``|λ_j(M̃) - λ̂_j| <= ρ = 2||E||²/(η + sqrt(η² + 4||E||²))`` (``||E||_2 <= ||E||_F``), so
    ``|λ_j(P) - λ̂_j| <= ρ + e`` (Weyl).  With ``s_D = (σ_A ± d_A, σ_C ± d_C)``::

        size >= ||λ̂ - s_D||_2 - 2(ρ + e),
        ||λ̂ - s_D||² = 2[(m_A - σ_A)² + (r_A - d_A)² + (m_C - σ_C)² + (r_C - d_C)²]

    and where ``η <= 0`` (order unknown) ``size >= |tr P - tr P_d| / 2 - 2e`` (Cauchy-Schwarz).

    **Eigenvectors.**  ``w_j = Vᵀ u_Dj`` (per decision) with halves ``w_{j,A}``, ``w_{j,C}``.  For
    ``j`` in ``A`` (``j = 1, 2``; ``C`` alike, roles swapped) and ``y_j`` the eigenvectors of ``A``,
    the projector ``(A - a_2)/(a_1 - a_2)`` on ``y_1`` gives ``|y_{1,2}·w|² = ½(||w_A||² ±
    t/r_A)``, ``t = p h_A + q b_A``, ``p = w_0² - w_1²``, ``q = 2 w_0 w_1`` (each ``t_j`` one row,
    its error ``(|p| + |q|) e`` added).  The unit eigenvector ``x = (x_A, x_C)`` of ``M̃`` for
    ``λ̃_j`` has ``||x_C|| <= ξ = ||E||/(η - ρ)`` (second block row) and ``x_A = α y_j + β y_k``
    with ``|β| <= ||E|| ξ / |a_k - λ̃_j| <= ||E|| ξ / γ`` (first block row times ``y_k``), where
    ``γ = min(2r_A, η) - 2(ρ + e)`` is at most ``2r_A - ρ`` and, less ``e``, at most the gap of
    ``λ̃_j`` to the other eigenvalues of the exact ``P``; so the computed ``P``'s eigenvector is
    within ``sin θ <= e/γ`` of ``x`` (Davis-Kahan), and ``Qᵀu_Dj`` within ``δ`` of ``w_j``::

        |u_Pj · u_Dj| <= |y_j·w_A| + |β| + ξ ||w_C|| + sin θ + δ    (||w_A|| <= 1)

    credited only where ``γ > τ_e = rtol (λmax + e) + e``: then ``λ_j`` of the computed ``P`` is
    in no tie group of :func:`covnet.core.metrics.ordered_eigh` (its eigenvector is LAPACK's up
    to sign) and every denominator above is positive.  ``sin θ`` is taken as ``τ_e/γ >= e/γ``:
    it reaches ``1`` (no credit) for ``0 < γ <= τ_e`` by itself, and ``γ <= 0`` gives ``+inf``
    or NaN (``fmin`` then takes ``1``).  Bound: ``size + max((n - Σ_j min(1, ·))/n - δ - 64 n
    eps, 0)``.
    """
    k = _svd_block_consts(P)
    if k.const is None:
        assert isinstance(P, _ChunkStage1P)  # the constants of the chunk form have no const
        R = k.coef @ P._gp()
    else:
        R = k.coef @ P._g
        R += k.const[:, None]
    r = R[2:4] * R[2:4]
    r += R[4:6] * R[4:6]
    np.sqrt(r, out=r)  # (r_A, r_C)
    E = R[7:11]
    E *= E
    e2 = _sum(E, 0)  # 4 ||E||_F²
    eta = r[0] + r[1]
    np.subtract(R[6], eta, out=eta)  # η (less the rounding, in the row)
    fallback = not _min(eta) > 0.0
    et = np.maximum(eta, 0.0) if fallback else eta
    rho = et * et
    rho += e2
    np.sqrt(rho, out=rho)
    rho += et
    if fallback:
        rho += TINY
    np.divide(e2, rho, out=rho)
    rho += k.c  # >= 2ρ + 2e + the size's rounding
    # size: sqrt(2 Σ (m - σ)² + (r - d)²) - 2ρ - 2e; |tr P - tr P_d| / 2 - 2e where η <= 0
    if fallback:
        tr = R[0] + R[1]
        np.abs(tr, out=tr)
    np.subtract(r, k.d, out=R[2:4])
    S = R[:4]
    S *= S
    size = _sum(S, 0)
    np.sqrt(size, out=size)
    size *= math.sqrt(2.0) * (1.0 - k.rel)
    if fallback:
        size = np.where(eta > 0.0, size, tr)
    size -= rho
    # orientation, per block (A, C) and eigenvalue (larger, smaller): T = |y_j·w_j|² first
    T = R[11:15].reshape(2, 2, -1)
    T /= r[:, None]
    T += k.half_n2
    np.sqrt(T, out=T)
    inv = rho * -0.5
    inv += eta
    np.maximum(inv, 0.0, out=inv)
    np.divide(1.0, inv, out=inv)  # 1/(η - ρ), +inf where not positive
    gam = r + r
    np.minimum(gam, eta, out=gam)
    gam -= rho  # γ
    np.maximum(gam, 0.0, out=gam)
    xi = e2 * inv
    xi *= 0.25  # ||E|| ξ
    xi += k.tie
    np.divide(xi, gam, out=gam)  # |β| + sin θ
    T += gam[:, None]
    np.sqrt(e2, out=e2)
    e2 *= inv  # 2ξ
    T += e2 * k.n_other
    np.fmin(T, 1.0, out=T)
    orient = _sum(T.reshape(4, -1), 0)
    orient *= -0.25
    orient += 1.0 - k.delta
    np.maximum(orient, 0.0, out=orient)
    size += orient
    return size


def _svd_consts(setup: _Setup, D: Mat) -> tuple[Mat, float, NDArray[np.intp], NDArray[np.intp]]:
    memo = setup.dc.memo
    if "svd" not in memo:
        s_D = setup.dc.eig()[0]
        pi, pj = _pairs(setup.n)
        memo["svd"] = (s_D, float(s_D.sum()), pi, pj)
    return memo["svd"]


def _D_inverse(setup: _Setup, D: Mat) -> tuple[Mat, float]:
    """``P_d⁻¹`` and ``κ_D = tr(P_d) tr(P_d⁻¹) >= cond(P_d)`` (cached per ``P_d``)."""
    return setup.dc.inverse()


def _svd_refine(P: Stage1P, D: Mat, ctx: BoundContext) -> Mat:
    """Size term from the stage-1 eigenvalues (Mirsky: the sorted eigenvalues move by
    ``<= ||ΔP||_F <= n err`` in 2-norm), plus a lower bound of the orientation term.

    With ``e = n err`` (plus solver rounding) bounding ``||ΔP||_2``: an eigenvalue separated from
    its neighbours by ``gap > 4e +`` twice the tie tolerance keeps its rank and is in no tie group
    in the exact ``P``, and by Davis-Kahan its exact eigenvector is within ``sqrt(2) e / (gap - e)``
    of the stage-1 one (up to sign), so ``|u_Pi · u_Di|`` exceeds the stage-1 value by at most
    that.  An eigenvector without such a gap is credited nothing (``|u_Pi · u_Di| <= 1``)."""
    n = P.n
    s_D, U_D = P.setup.dc.eig()
    w, U = np.linalg.eigh(P.stack())  # ascending
    size = _cov_slack(np.sqrt(((w[:, ::-1] - s_D) ** 2).sum(axis=-1)), n, ctx)
    e = n * ctx.err + 64.0 * n * EPS * ctx.scale
    gap = np.full(w.shape, np.inf)
    step = w[:, 1:] - w[:, :-1]
    gap[:, :-1] = step
    gap[:, 1:] = np.minimum(gap[:, 1:], step)
    need = 4.0 * e + 2.0 * EIG_TIE_RTOL * (np.abs(w).max(axis=1, keepdims=True) + e)
    dist = np.where(gap > need, np.sqrt(2.0) * e / (gap - e), 1.0)
    cos = np.abs(np.einsum("bki,ki->bi", U, U_D[:, ::-1]))
    orient: Mat = (n - np.minimum(cos + dist, 1.0).sum(axis=1)) / n - 64.0 * n * EPS
    return size + np.maximum(orient, 0.0)


def _logdet_spd(A: Mat) -> float:
    """``log det A`` of one SPD matrix from its Cholesky factor (NaN unless SPD)."""
    if A.size == 0:
        return 0.0
    c, info = lapack.dpotrf(A, lower=1)
    return float(2.0 * np.log(np.diagonal(c)).sum()) if info == 0 else np.nan


_LOG2 = math.log(2.0)


def _logdet_spd2(a: float, b: float, c: float) -> float:
    """``log det [[a, b], [b, c]]`` from its Cholesky factor (NaN unless positive definite)."""
    if not a > 0.0:
        return math.nan
    l10 = b / math.sqrt(a)
    d = c - l10 * l10
    return math.log(a) + math.log(d) if d > 0.0 else math.nan


def _spd_inverse_logdet(A: Mat) -> tuple[Mat, float]:
    """:func:`spd_inverse` of one SPD matrix and its ``log det`` (:func:`_logdet_spd`) from one
    Cholesky factorisation (the same factor both compute)."""
    c, info = _dpotrf(A, lower=1)
    if info != 0:
        return spd_inverse(A), np.nan  # raises
    ld = float(2.0 * np.log(np.diagonal(c)).sum())
    inv, info = _dpotri(c, lower=1)
    if info != 0:
        raise np.linalg.LinAlgError(f"matrix is not positive definite (LAPACK info {info})")
    lo, hi = _tril(A.shape[0])
    inv[hi, lo] = inv[lo, hi]
    return inv, ld


def _logdet_bound(P: Stage1P, D: Mat, ctx: BoundContext) -> Mat:
    """The stage-1 value of ``log det((P+D)/2) - ½ log det P - ½ log det D`` via the reduced
    form: with ``v`` the non-support coordinates, ``W = P∞ + D`` and ``V = Kᵀ W⁻¹ K``,
    ``det P_i = det(P∞[v, v]) / det Z_i`` and ``det(P_i + D) = det W det(Z_i + V) / det Z_i``, so

        f_i = c + log det(Z_i + V) - ½ log det Z_i,
        c = log det W - n log 2 - ½ log det P∞[v, v] - ½ log det D,

    deflated by the effect of the stage-1 error of ``P∞`` and by rounding relative to the
    condition numbers of ``P_i``, ``P_d`` and ``W``."""
    st = P.setup
    if "logdet" not in st.memo:
        n, r = st.n, st.r
        P_inf = st.P_inf.reshape(n, n)
        W = P_inf + D
        W_inv, ld_W = _spd_inverse_logdet(W)
        V = st.KT @ W_inv @ st.KT.T
        if st._py is not None and n == 4:  # P∞[v, v] is 2 x 2: its Cholesky factor by hand
            v0, v1 = (j for j in range(n) if j not in st.s.tolist())
            Pl = P_inf.tolist()
            ld_vv = _logdet_spd2(Pl[v0][v0], Pl[v0][v1], Pl[v1][v1])
        else:
            v = np.ones(n, dtype=bool)
            v[st.s] = False
            ld_vv = _logdet_spd(P_inf[v][:, v])
        c = ld_W - n * _LOG2 - 0.5 * ld_vv - 0.5 * st.dc.logdet()
        D_inv, kappa_D = _D_inverse(st, D)
        tr_D_inv = kappa_D / st.dc.trace
        kappa_W = (ctx.lam_max + st.dc.trace) * tr_D_inv  # >= cond(W)
        lam_lo = min(ctx.lam_min, 1.0 / tr_D_inv)  # <= λmin of P∞[v, v], W, P_i
        # P∞ (so W and P∞[v, v]) carries the stage-1 error err: |Δ log det X| <= n² err / λmin;
        # the rest is rounding, relative to the condition numbers involved
        slack = 2.0 * n * n * ctx.err / lam_lo
        rel = ERR_FACTOR * n * n * EPS * (ctx.kappa + kappa_D + kappa_W)
        mag = 1.0 + abs(ld_W) + abs(ld_vv) + abs(c) + float(r)
        st.memo["logdet"] = (c, V.reshape(r * r), slack + rel * mag, rel)
    c, Vf, slack, rel = st.memo["logdet"]
    if isinstance(P, _ChunkStage1P):
        # det(Z_i + V) and det Z_i in one product (det_row of C⁻¹ + V and of C⁻¹ on Q); the
        # metric is >= 0, so a negative value needs no deflation of its own and val·(1 - rel)
        # - slack (<= val - rel |val| - slack for val >= 0, < 0 otherwise) is a valid bound
        b = P.setup._base4()
        Cm = np.array(
            P.setup.det_row(tuple(x + y for x, y in zip(b, Vf.tolist(), strict=True)))
            + P.setup.det_row(b)
        )
        R = Cm.reshape(2, 6) @ P.Q
        x = R[0]
        x /= np.sqrt(R[1])
        lb: Mat = np.log(x, out=x)
        lb *= 1.0 - rel
        lb += c * (1.0 - rel) - slack
        return lb
    val: Mat
    if st.r == 2:
        assert P.det is not None  # Stage1P has det Z_i when r = 2
        ZV = P.Z + Vf[:, None]
        val = c + np.log((ZV[0] * ZV[3] - ZV[1] * ZV[2]) / np.sqrt(P.det))
    else:
        val = c + _logdet_soa(P.Z + Vf[:, None], st.r) - 0.5 * _logdet_soa(P.Z, st.r)
    return val - (slack + rel * np.abs(val))


def _kl_bound(P: Stage1P, D: Mat, ctx: BoundContext) -> Mat:
    """The stage-1 value of ``¼[tr(D⁻¹P) + tr(P⁻¹D) - 2n]``: ``tr(D⁻¹P_i)`` is linear in the
    stage-1 entries and ``tr(P_i⁻¹ D) = tr((P⁻¹ + J_i) D) = tr(Y0 D) + vec(D[s, s]) ·
    (Z_i - C⁻¹)`` is linear in ``Z_i`` (the information form, exact up to rounding); deflated by
    ``¼ sum|D⁻¹| err`` for the first and by rounding relative to the condition numbers."""
    st = P.setup
    D_inv, kappa_D = _D_inverse(st, D)
    if "kl" not in st.memo:
        n, s = st.n, st.s
        D_inv_f = D_inv.reshape(n * n)
        d_ss = D[s][:, s].reshape(s.size * s.size)
        c2 = float((st.Y0 * D).sum()) - float(d_ss @ st.Zc.reshape(s.size * s.size))
        st.memo["kl"] = (D_inv_f @ st.T, float(D_inv_f @ st.P_inf), d_ss, c2)
    w1, c1, d_ss, c2 = st.memo["kl"]
    t1 = w1 @ P._g + c1
    t2 = d_ss @ P.Z + c2
    val = 0.25 * (t1 + t2 - 2 * P.n)
    # t1 is linear in the stage-1 entries (each off by <= err); the rest is rounding, relative
    # to the condition numbers of P_i and P_d
    rel = ERR_FACTOR * P.n * P.n * EPS * (ctx.kappa + kappa_D)
    slack = 0.25 * (float(np.abs(D_inv).sum()) * ctx.err + rel * (np.abs(t1) + np.abs(t2) + P.n))
    return val - (slack + rel * np.abs(val))


# the lower bounds used by :func:`fast_search`, one per built-in metric (its entry's
# ``subset_bound`` in :data:`covnet.core.metrics.METRICS`).  A metric without one (or a user's
# own function) is searched by the batched exhaustive fallback, still exact.
ABS_TRACE_BOUND = MetricBound(_abs_trace_bound)
TRACE_DIFF_BOUND = MetricBound(_trace_diff_bound)
FROBENIUS_BOUND = MetricBound(_frobenius_bound)
ONE_NORM_BOUND = MetricBound(_one_norm_bound)
INF_NORM_BOUND = MetricBound(_inf_norm_bound)
SPECTRAL_BOUND = MetricBound(_spectral_cheap, _spectral_refine)
SVD_BOUND = MetricBound(_svd_cheap, _svd_refine, refine_seed=lambda n: n != 4)
LOGDET_BOUND = MetricBound(_logdet_bound)
KL_BOUND = MetricBound(_kl_bound)


def _chol_soa(A: Mat) -> list[list[Mat]]:
    """Column Cholesky of ``(r, r, B)`` SPD matrices entry by entry: ``L[i][j]`` ``(B,)`` for
    ``i >= j``.  A non-positive pivot gives NaN (the callers ignore floating-point errors)."""
    n = A.shape[0]
    L: list[list[Mat]] = [[A[0, 0]] * n for _ in range(n)]
    for j in range(n):
        piv = A[j, j]
        for k in range(j):
            piv = piv - L[j][k] * L[j][k]
        d = np.sqrt(piv)
        L[j][j] = d
        for i in range(j + 1, n):
            v = A[i, j]
            for k in range(j):
                v = v - L[i][k] * L[j][k]
            L[i][j] = v / d
    return L


def _logdet_soa(Z: Mat, r: int) -> Mat:
    """``log det`` of ``(r*r, B)`` SPD matrices (``0`` for ``r = 0``)."""
    if r == 0:
        return np.zeros(Z.shape[1])
    L = _chol_soa(Z.reshape(r, r, -1))
    ld: Mat = 2.0 * np.log(np.prod([L[i][i] for i in range(r)], axis=0))
    return ld


def _spd_inverse_soa(Z: Mat, r: int) -> Mat:
    """Inverses of SPD ``r x r`` matrices stored as columns of ``Z (r*r, B)`` (row-major
    entries); closed form for ``r = 1``, column Cholesky otherwise.  Rounding trouble shows as
    NaN/inf, which the bounds turn into "no information"."""
    if r == 0:
        return Z
    if r == 1:
        return 1.0 / Z
    A = Z.reshape(r, r, -1)
    L = _chol_soa(A)
    M: list[list[Mat]] = [[A[0, 0]] * r for _ in range(r)]  # M = L⁻¹, lower triangular
    for i in range(r):
        M[i][i] = 1.0 / L[i][i]
        for j in range(i - 1, -1, -1):
            v = L[i][j] * M[j][j]
            for k in range(j + 1, i):
                v = v + L[i][k] * M[k][j]
            M[i][j] = -v * M[i][i]
    out = np.empty_like(A)
    for c in range(r):  # (L⁻ᵀ L⁻¹)_cd = sum_{k >= max(c, d)} M_kc M_kd
        for d in range(c, r):
            acc = M[d][c] * M[d][d]
            for k in range(d + 1, r):
                acc = acc + M[k][c] * M[k][d]
            out[c, d] = acc
            out[d, c] = acc
    return out.reshape(r * r, -1)


# --------------------------------------------------------------------------------------------
# the search
# --------------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=2 * (CHUNK_BITS + 1))
def _bit_table(k: int) -> tuple[Mat, NDArray[np.int64]]:
    """Constant tables for k bits: ``(k, 2^k)`` 0/1 floats (column t holds the bits of t) and
    the popcount of every t."""
    t = np.arange(1 << k, dtype=np.int64)
    bits = ((t[None, :] >> np.arange(k)[:, None]) & 1).astype(np.float64)
    pc = bits.sum(axis=0).astype(np.int64)
    bits.flags.writeable = False
    pc.flags.writeable = False
    return bits, pc


class SearchResult(NamedTuple):
    subset: tuple[int, ...]
    value: float
    P: Mat
    n_feasible: int
    n_evaluated: int


class _Exact:
    """Exact values, with the reference's arithmetic, of feasible subsets given as rows of
    ``codes`` (codes over the free sensors, :class:`SearchTables`)."""

    def __init__(
        self, Y0: Mat, P_d: Mat, metric: MetricFn, tab: SearchTables, codes: NDArray[np.int64]
    ) -> None:
        self.Y0, self.P_d, self.metric, self.tab, self.codes = Y0, P_d, metric, tab, codes
        # the plan's exact J_i table applies when the rows index the plan's own codes
        self.table = tab.J is not None and codes is tab.codes

    def masks(self, rows: NDArray[np.intp]) -> NDArray[np.bool_]:
        if self.table:
            assert self.tab.masks is not None  # the plan's own codes: a single-chunk plan
            return self.tab.masks[rows]
        return self.tab.code_masks(self.codes[rows])

    def covariances(self, rows: NDArray[np.intp], masks: NDArray[np.bool_]) -> Mat:
        """``P_i = (P⁻¹ + J_i)⁻¹`` exactly as :func:`~covnet.core.allocation.subset_covariance`."""
        if self.table:
            assert self.tab.J is not None  # self.table says so
            J = self.tab.J[rows]
        else:
            J = gain_sums(self.tab.gains, masks)
        return spd_inverse(self.Y0 + J)

    def values(self, P: Mat) -> NDArray[np.float64]:
        v = np.asarray(self.metric(P, self.P_d), dtype=np.float64)
        if v.shape != P.shape[:1]:
            raise ValueError(f"metric returned shape {v.shape} for a batch of {P.shape[0]}")
        if not np.isfinite(v).all():
            raise ValueError("metric returned a non-finite value")
        return v


def fast_search(
    P_pred: Mat,
    P_d: Mat,
    metric: MetricFn,
    bound: MetricBound | None,
    tab: SearchTables,
    tie_rtol: float,
    batch_invariant: bool = False,
) -> SearchResult:
    """Exact argmin with the tie rule (module docstring); the inputs are already validated and
    ``tab`` holds the gain-only part of the problem."""
    n_feasible = tab.n_feasible
    Y0 = _spd_inverse_one(P_pred)
    if bound is None:
        return _batched_exhaustive(Y0, P_d, metric, tab, tie_rtol)

    # ---- stage 1: a cheap lower bound for every feasible subset
    with np.errstate(all="ignore"):  # a NaN bound means "no information", handled below
        st = _Setup(P_pred, P_d, Y0, tab)
        S1: Stage1P | None = None
        if tab.chunk:
            assert tab.codes is not None  # a single-chunk plan
            codes = tab.codes
            S1 = st.chunk_covariances()
            lb = bound.cheap(S1, P_d, st.ctx)
        else:
            codes, lb = _stage1(st, bound.cheap, P_d, tab)
    best = int(lb.argmin())  # the first NaN, if any
    L = float(lb[best])
    if L != L:  # NaN: no information from those bounds
        lb[np.isnan(lb)] = -np.inf
        L = -np.inf
        best = int(lb.argmin())

    # ---- stage 2: exact values in increasing-bound order while they can still tie
    refined = np.zeros(lb.size, dtype=bool) if bound.refine is not None else None
    seed = bound.refine_seed
    if callable(seed):
        seed = seed(tab.n)
    if refined is not None and lb.size > (SEED_POOL if seed else SEED_POOL_ABOVE):
        # a better first candidate: the best refined bound among the best cheap ones (a larger
        # pool for small problems, where the refinement's fixed cost dominates)
        size = SEED_POOL if lb.size > 1024 else min(SMALL_SEED_POOL, lb.size - 1)
        pool = np.argpartition(lb, size)[:size]
        assert bound.refine is not None  # refined is kept exactly when there is a refine bound
        with np.errstate(all="ignore"):
            lb2 = bound.refine(st.take(S1, pool, codes), P_d, st.ctx)
        lb[pool] = np.fmax(lb[pool], lb2)
        refined[pool] = True
        best = int(lb.argmin())
    # the plan's exact J_i (the reference's sums, looked up) when the rows are the plan's codes
    table = tab.J is not None and codes is tab.codes
    if table:
        assert tab.J is not None  # table says so
        P_best = _spd_inverse_one(Y0 + tab.J[best])
    else:
        ex = _Exact(Y0, P_d, metric, tab, codes)
        P_best = ex.covariances(np.array([best]), ex.masks(np.array([best])))[0]
    U = _single_value(metric, P_best, P_d)  # called as the reference calls it
    # a metric not known to be batch-invariant may differ in the last bits between the batched
    # calls below and the reference's single calls: prune with a margin, recheck near ties
    margin = 0.0 if batch_invariant else 1e-6
    tau = _threshold(U, L, tie_rtol, margin)
    lb[best] = np.inf  # evaluated
    if table and not _min(lb) <= tau:  # the common case: one exact evaluation settles it
        assert tab.subsets is not None  # a plan with the J table is single-chunk
        return SearchResult(tab.subsets[best], U, P_best, n_feasible, 1)
    cand = (lb <= tau).nonzero()[0]
    if table:
        ex = _Exact(Y0, P_d, metric, tab, codes)
    best_mask = ex.masks(np.array([best]))
    if cand.size == 0:
        return SearchResult(tuple(best_mask[0].nonzero()[0].tolist()), U, P_best, n_feasible, 1)
    ev_masks, ev_P, ev_v = [best_mask], [P_best[None]], [np.array([U])]

    def evaluate(rows: NDArray[np.intp]) -> float:
        """Exact values of ``rows``; returns the new tau.  Evaluated rows get bound +inf."""
        nonlocal U
        masks = ex.masks(rows)
        P_ev = ex.covariances(rows, masks)
        v_ev = ex.values(P_ev)
        ev_masks.append(masks)
        ev_P.append(P_ev)
        ev_v.append(v_ev)
        lb[rows] = np.inf
        U = min(U, float(v_ev.min()))
        return _threshold(U, L, tie_rtol, margin)

    cand = cand[np.argsort(lb[cand], kind="stable")]
    if refined is not None:
        assert bound.refine is not None  # refined is kept exactly when there is a refine bound
        # refine the bounds in cheap-bound order, evaluating each block's best refined few
        # exactly at once so that tau falls early; blocks grow from REFINE_BLOCK (a small first
        # block when tau is still loose, large ones for throughput)
        lo, block = 0, REFINE_BLOCK
        while lo < cand.size:
            rows = cand[lo : lo + block]
            lo += block
            block = min(4 * block, EXACT_BLOCK)
            rows = rows[lb[rows] <= tau]
            if rows.size == 0:
                break  # sorted: every later cheap bound exceeds tau too
            todo = rows[~refined[rows]]
            if todo.size:
                with np.errstate(all="ignore"):
                    lb2 = bound.refine(st.take(S1, todo, codes), P_d, st.ctx)
                lb[todo] = np.fmax(lb[todo], lb2)  # a NaN refinement keeps the cheap bound
            rows = rows[lb[rows] <= tau]
            if rows.size:
                tau = evaluate(rows[np.argsort(lb[rows], kind="stable")[:REFINED_PICKS]])
        cand = cand[lb[cand] <= tau]
        cand = cand[np.argsort(lb[cand], kind="stable")]
    # exact values in increasing-bound order, blocks of growing size, while they can still tie
    pos, block = 0, min(32, EXACT_BLOCK)
    while pos < cand.size and lb[cand[pos]] <= tau:
        rows = cand[pos : pos + block]
        tau = evaluate(rows[lb[rows] <= tau])
        pos += block
        block = min(4 * block, EXACT_BLOCK)
    if len(ev_v) == 1 and table and not margin:  # the refined bounds pruned every candidate
        assert tab.subsets is not None  # a plan with the J table is single-chunk
        return SearchResult(tab.subsets[best], U, P_best, n_feasible, 1)
    all_masks, all_P, all_v = (np.concatenate(x) for x in (ev_masks, ev_P, ev_v))
    if margin:
        _recheck_singly(all_v, all_P, metric, P_d, tie_rtol, margin)
    k = tie_select(all_v, all_masks, tie_rtol)
    subset = tuple(all_masks[k].nonzero()[0].tolist())
    return SearchResult(subset, float(all_v[k]), all_P[k], n_feasible, int(all_v.size))


def _single_value(metric: MetricFn, P: Mat, P_d: Mat) -> float:
    """``f(P, P_d)`` for one ``(n, n)`` matrix, exactly as the reference calls the metric."""
    # a metric returns a float64 scalar for one matrix (the built-in ones do), typed as an array
    f: NDArray[np.float64] | np.float64 = metric(P, P_d)
    v = float(f) if type(f) is np.float64 else float(np.asarray(f, dtype=np.float64))
    if not math.isfinite(v):
        raise ValueError("metric returned a non-finite value")
    return v


def _recheck_singly(
    values: Mat, P: Mat, metric: MetricFn, P_d: Mat, tie_rtol: float, margin: float
) -> None:
    """Replace, in place, the values within ``margin`` (relative) of the tie threshold by one
    call per subset, as the reference computes them."""
    f0 = float(values.min())
    near = (values <= tie_threshold(f0, tie_rtol) + margin * max(abs(f0), TINY)).nonzero()[0]
    for q in near.tolist():
        values[q] = _single_value(metric, P[q], P_d)


def _threshold(U: float, L: float, tie_rtol: float, margin: float = 0.0) -> float:
    """``τ = U + (rtol + margin) · max(|U|, |L|, tiny)`` >= the reference's tie threshold
    whenever the minimum ``f*`` lies in ``[L, U]``; ``+inf`` (no pruning) without a finite
    ``L``."""
    if L == -np.inf:
        return np.inf
    return U + (tie_rtol + margin) * max(abs(U), abs(L), TINY)


def _stage1(
    st: _Setup, bound_fn: BoundFn, P_d: Mat, tab: SearchTables
) -> tuple[NDArray[np.int64], Mat]:
    """Codes of every feasible subset and their cheap lower bounds, chunk by chunk: the low
    ``c`` bits of a code vary within a chunk, the high bits are fixed per chunk."""
    c = CHUNK_BITS
    kmin, kmax, pc_lo, pc_hi = tab.kmin, tab.kmax, tab.pc_lo, tab.pc_hi
    assert pc_lo is not None and pc_hi is not None  # a plan of several chunks
    assert tab.S_lo is not None and tab.S_hi is not None
    Z_lo = tab.S_lo + st.base[:, None]
    Z_hi = tab.S_hi
    codes_parts, lb_parts = [], []
    for h in range(pc_hi.size):
        lo, hi = kmin - int(pc_hi[h]), kmax - int(pc_hi[h])
        if hi < 0 or lo > c:
            continue
        if lo <= 0 and hi >= c:
            t = np.arange(1 << c)
            Z = Z_lo
        elif lo == 1 and hi >= c:  # all but the empty low part
            t = np.arange(1, 1 << c)
            Z = Z_lo[:, 1:]
        else:
            t = ((pc_lo >= lo) & (pc_lo <= hi)).nonzero()[0]
            Z = Z_lo[:, t]
        if h:
            Z = Z + Z_hi[:, h : h + 1]
            t = t + (h << c)
        lb_parts.append(bound_fn(st.covariances(Z), P_d, st.ctx))
        codes_parts.append(t)
    if len(lb_parts) == 1:
        return codes_parts[0], lb_parts[0]
    return np.concatenate(codes_parts), np.concatenate(lb_parts)


def _batched_exhaustive(
    Y0: Mat, P_d: Mat, metric: MetricFn, tab: SearchTables, tie_rtol: float
) -> SearchResult:
    """Every feasible subset with exact ``P_i``, the metric called on batches.  Values within a
    relative 1e-6 of the tie threshold are recomputed one subset per call, as the reference
    calls the metric, so a metric whose batched and single results differ in the last bits still
    selects the reference's subset."""
    if tab.chunk:
        assert tab.codes is not None
        codes = tab.codes
    else:  # code = h << CHUNK_BITS | t: row h, column t
        assert tab.pc_lo is not None and tab.pc_hi is not None
        pcs = tab.pc_lo[None, :] + tab.pc_hi[:, None]
        codes = ((pcs >= tab.kmin) & (pcs <= tab.kmax)).reshape(-1).nonzero()[0]
    ex = _Exact(Y0, P_d, metric, tab, codes)
    parts_v = []
    for lo in range(0, codes.size, EXACT_BLOCK):
        rows = np.arange(lo, min(lo + EXACT_BLOCK, codes.size))
        parts_v.append(ex.values(ex.covariances(rows, ex.masks(rows))))
    vals = np.concatenate(parts_v)
    f0 = float(vals.min())
    near = (vals <= tie_threshold(f0, tie_rtol) + 1e-6 * max(abs(f0), TINY)).nonzero()[0]
    masks = ex.masks(near)
    P_near = ex.covariances(near, masks)
    single = np.array([_single_value(metric, P_q, P_d) for P_q in P_near])
    k = tie_select(single, masks, tie_rtol)
    subset = tuple(masks[k].nonzero()[0].tolist())
    return SearchResult(subset, float(single[k]), P_near[k], tab.n_feasible, tab.n_feasible)
