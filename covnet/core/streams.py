"""Named, counter-based random streams: every draw comes from an explicit ``Generator``.

A stream is keyed by the run seed and a tuple of small integers, ``SeedSequence(seed,
spawn_key=key)``, so the noise of sensor ``j`` at scan ``k`` is the same whichever process draws
it, in whatever order, after whatever restart.  Domains keep the uses apart.

**Seeding in blocks** (:func:`seed_words`).  A ``PCG64`` seeded from a ``SeedSequence`` takes
four 64-bit words of it, ``generate_state(4, uint64)``, and nothing else.  Building the
``SeedSequence`` and those words costs about 11 us in numpy (most of a generator's 15-23 us),
once per sensor and scan: 256 sensors over 20 000 scans are 77 s of it.  The words are a fixed
hash of the seed and the key (numpy's ``SeedSequence``, after M. O'Neill's ``seed_seq_fe``;
stable by numpy's policy on reproducibility), so :func:`stream` computes them for a block of
:data:`BLOCK` consecutive last key entries at once, in ``uint32`` numpy arithmetic (wrapping
modulo 2^32 as the C code does), remembers the block (:data:`BLOCKS_KEPT`), and seeds each
``PCG64`` from its row: the same generator, bit for bit, for about 3.5 us.  Only keys and seeds
the block path is checked for take it (non-negative Python ``int`` seed, every key entry a
Python ``int`` in ``[0, 2^32)``); anything else, or a numpy whose words differ from these (a
start-up check against ``SeedSequence`` itself), is seeded by ``SeedSequence`` as before.
"""

from __future__ import annotations

import threading
from typing import Any, cast

import numpy as np
from numpy.random.bit_generator import ISeedSequence

TRUTH = 0  #: process noise of the target trajectories
INITIAL = 1  #: the filter's initial estimate
SENSOR = 2  #: measurement noise: key (SENSOR, sensor_index, scan)
POLICY = 20  #: a stochastic allocation policy's draws: key (POLICY, scan)

#: consecutive last key entries whose seed words are computed together
BLOCK = 256
#: blocks remembered (8 kB each); the oldest goes first
BLOCKS_KEPT = 1024

# numpy's SeedSequence constants (bit_generator.pyx: seed_seq_fe of randutils)
_POOL = 4
_INIT_A, _MULT_A = 0x43B0D7E5, 0x931E8875
_INIT_B, _MULT_B = 0x8B51F9DD, 0x58F38DED
_MIX_L, _MIX_R = 0xCA01F9DD, 0x4973F715
_XSHIFT = 16
_U32 = np.uint32
_WORD = 1 << 32


def _int_words(n: int) -> list[int]:
    """``n >= 0`` as little-endian 32-bit words, at least one (numpy's ``_int_to_uint32_array``)."""
    out = [n & 0xFFFFFFFF]
    n >>= 32
    while n:
        out.append(n & 0xFFFFFFFF)
        n >>= 32
    return out


def seed_words(seed: int, keys: Any) -> np.ndarray:
    """``SeedSequence(seed, spawn_key=row).generate_state(4, uint64)`` for every row of
    ``keys`` ``(m, K)`` (entries in ``[0, 2^32)``, ``seed >= 0``): ``(m, 4)`` ``uint64``.

    The entropy is the seed's 32-bit words, padded with zeros to the pool size (4), then the
    key's entries.  With ``hashmix(v) = h ← h·A;  v ← (v ⊕ h_old)·h;  v ⊕ (v >> 16)`` (``h``
    from ``INIT_A``) and ``mix(x, y) = r ⊕ (r >> 16)``, ``r = L·x − R·y``, all modulo 2^32::

        pool_i = hashmix(entropy_i)                                  i < 4
        pool_d = mix(pool_d, hashmix(pool_s))         for s, then d ≠ s, in 0..3
        pool_d = mix(pool_d, hashmix(entropy_s))      for s ≥ 4, then d in 0..3

    and the 8 output words ``w_i = (p ⊕ h)·h' ⊕ ((p ⊕ h)·h' >> 16)`` with ``p = pool_{i mod 4}``,
    ``h`` from ``INIT_B`` multiplied by ``MULT_B`` before each (``h'``), paired into 4
    little-endian 64-bit words.  Rows are columns of one array: every step is elementwise."""
    k = np.asarray(keys, dtype=np.uint64)
    if k.ndim != 2 or k.shape[1] == 0:
        raise ValueError(f"keys: expected a non-empty (m, K) array, got shape {k.shape}")
    m = k.shape[0]
    run = _int_words(seed)
    run += [0] * (_POOL - len(run))
    entropy = [np.full(m, w, dtype=_U32) for w in run]
    entropy += [k[:, c].astype(_U32) for c in range(k.shape[1])]
    h = [_U32(_INIT_A)]

    def hashmix(v: Any) -> Any:  # uint32 arrays (numpy's stubs lose the dtype)
        v = v ^ h[0]
        h[0] = h[0] * _U32(_MULT_A)
        v = v * h[0]
        return v ^ (v >> _U32(_XSHIFT))

    def mix(x: Any, y: Any) -> Any:
        r = _U32(_MIX_L) * x - _U32(_MIX_R) * y
        return r ^ (r >> _U32(_XSHIFT))

    with np.errstate(over="ignore"):  # the hash wraps modulo 2^32 by design
        pool = [hashmix(entropy[i]) for i in range(_POOL)]
        for s in range(_POOL):
            for d in range(_POOL):
                if s != d:
                    pool[d] = mix(pool[d], hashmix(pool[s]))
        for s in range(_POOL, len(entropy)):
            for d in range(_POOL):
                pool[d] = mix(pool[d], hashmix(entropy[s]))
        out = np.empty((m, 8), dtype=_U32)
        hb = _U32(_INIT_B)
        for i in range(8):
            v = pool[i % _POOL] ^ hb
            hb = hb * _U32(_MULT_B)
            v = v * hb
            out[:, i] = v ^ (v >> _U32(_XSHIFT))
    return cast(np.ndarray, out.view("<u8").astype(np.uint64))


class _Words(ISeedSequence):
    """A seed sequence that hands ``PCG64`` its four precomputed words (:func:`seed_words`); a
    request for anything else is the real ``SeedSequence``'s."""

    __slots__ = ("words", "seed", "key")

    def __init__(self, words: np.ndarray, seed: int, key: tuple[int, ...]) -> None:
        self.words, self.seed, self.key = words, seed, key

    def generate_state(self, n_words: int, dtype: Any = np.uint32) -> np.ndarray:
        if n_words == 4 and np.dtype(dtype) == np.uint64:
            return self.words.copy()
        real = np.random.SeedSequence(self.seed, spawn_key=self.key)
        return np.asarray(real.generate_state(n_words, dtype))


def _seeded(words: np.ndarray, seed: int, key: tuple[int, ...]) -> Any:
    """:class:`_Words` as ``PCG64`` takes it (its stubs name ``SeedSequence`` only, though any
    ``ISeedSequence`` is taken)."""
    return _Words(words, seed, key)


_blocks: dict[tuple[int, tuple[int, ...], int], np.ndarray] = {}
_blocks_lock = threading.Lock()
_checked: list[bool] = []  # [] before the start-up check, then [whether the block path holds]


def _reference(seed: int, key: tuple[int, ...]) -> np.random.Generator:
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(seed, spawn_key=key)))


def _block_path_holds() -> bool:
    """Whether this numpy seeds ``PCG64`` as :func:`seed_words` says (checked once: a seed of
    several words, keys of one to four entries, the generators' first draws compared)."""
    if not _checked:
        ok = True
        for seed, key in ((2026, (SENSOR, 5, 77)), (2**70 + 3, (7,)), (0, (1, 2, 3, 2**32 - 1))):
            words = seed_words(seed, [key])[0]
            fast = np.random.Generator(np.random.PCG64(_seeded(words, seed, key)))
            ok = ok and np.array_equal(fast.random(4), _reference(seed, key).random(4))
        _checked.append(ok)
    return _checked[0]


def _words_of(seed: int, key: tuple[int, ...]) -> np.ndarray | None:
    """The seed words of ``(seed, key)`` from its block (computed on first use), or None where
    the block path does not apply (module docstring)."""
    if type(seed) is not int or seed < 0 or not key:
        return None
    for v in key:
        if type(v) is not int or not 0 <= v < _WORD:
            return None
    if not _block_path_holds():
        return None
    head, last = key[:-1], key[-1]
    tag = (seed, head, last // BLOCK)
    block = _blocks.get(tag)
    if block is None:
        first = last - last % BLOCK
        lasts = np.arange(first, min(first + BLOCK, _WORD), dtype=np.uint64)
        keys = np.empty((lasts.size, len(key)), dtype=np.uint64)
        keys[:, : len(head)] = np.asarray(head, dtype=np.uint64)
        keys[:, -1] = lasts
        block = seed_words(seed, keys)
        with _blocks_lock:
            while len(_blocks) >= BLOCKS_KEPT:
                _blocks.pop(next(iter(_blocks)))
            _blocks[tag] = block
    return cast(np.ndarray, block[last % BLOCK])


def stream(seed: int, *key: int) -> np.random.Generator:
    """A fresh PCG64 generator for ``(seed, key)``; independent of every other key.  The same
    generator as ``Generator(PCG64(SeedSequence(seed, spawn_key=key)))``, seeded in blocks
    (module docstring)."""
    words = _words_of(seed, key)
    if words is None:
        return _reference(seed, key)
    return np.random.Generator(np.random.PCG64(_seeded(words, seed, key)))


def sensor_stream(seed: int, sensor_index: int, scan: int) -> np.random.Generator:
    """The generator sensor ``sensor_index`` draws its scan-``scan`` measurement noise from."""
    return stream(seed, SENSOR, sensor_index, scan)


def policy_stream(seed: int, scan: int) -> np.random.Generator:
    """The generator a stochastic allocation policy (``random``) draws scan ``scan``'s choice
    from: the same in every process and episode, whatever was decided before."""
    return stream(seed, POLICY, scan)
