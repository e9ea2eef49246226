"""Streams seeded in blocks (:mod:`covnet.core.streams`): the same generators, bit for bit, as
``Generator(PCG64(SeedSequence(seed, spawn_key=key)))``, whatever the seed, key or block."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from covnet.core import streams


def reference(seed, key):
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(seed, spawn_key=key)))


def draws(g: np.random.Generator) -> list[np.ndarray]:
    """Draws of several kinds, in order (each consumes the stream differently)."""
    return [g.standard_normal(3), g.random(2), g.integers(0, 1000, 3), g.poisson(2.5, 3)]


def same(a: np.random.Generator, b: np.random.Generator) -> bool:
    return all(np.array_equal(x, y) for x, y in zip(draws(a), draws(b), strict=True))


@settings(max_examples=300, deadline=None)
@given(
    seed=st.one_of(st.integers(0, 2**32 - 1), st.integers(0, 2**80)),
    key=st.lists(st.integers(0, 2**32 - 1), min_size=1, max_size=5).map(tuple),
)
def test_the_block_path_draws_what_seedsequence_seeds(seed, key):
    assert same(streams.stream(seed, *key), reference(seed, key))


def test_seed_words_are_seedsequence_words_across_blocks_and_edges():
    lasts = [0, 1, 255, 256, 257, 511, 20_000, 2**31, 2**32 - 2, 2**32 - 1]
    for seed in (0, 1, 2026, 2**32 - 1, 2**32, 2**64 + 7, 2**127 + 12345):
        for head in ((), (streams.SENSOR,), (streams.SENSOR, 255), (9, 8, 7, 6)):
            keys = np.array([(*head, last) for last in lasts], dtype=np.uint64)
            got = streams.seed_words(seed, keys)
            want = [
                np.random.SeedSequence(seed, spawn_key=tuple(int(v) for v in row)).generate_state(
                    4, np.uint64
                )
                for row in keys
            ]
            assert got.dtype == np.uint64 and np.array_equal(got, np.array(want)), (seed, head)
            for row in keys:  # and the generators the cached blocks seed
                key = tuple(int(v) for v in row)
                assert same(streams.stream(seed, *key), reference(seed, key)), (seed, key)


def test_every_scan_of_a_sensor_in_a_long_run():
    for k in range(1, 3001):
        a, b = streams.sensor_stream(2026, 17, k), reference(2026, (streams.SENSOR, 17, k))
        assert np.array_equal(a.standard_normal(2), b.standard_normal(2)), k


def test_keys_the_block_path_does_not_take_are_seeded_as_before():
    """Entries of 2^32 and more (several words), numpy integers and bools go to SeedSequence
    itself; a negative seed or entry is refused as SeedSequence refuses it."""
    for seed, key in (
        (5, (2**32,)),
        (5, (1, 2**40 + 3)),
        (5, (np.int64(3), 4)),
        (np.int64(7), (1, 2)),
        (5, (True, 2)),
    ):
        assert same(streams.stream(seed, *key), reference(seed, key)), (seed, key)
    for seed, key in ((-1, (1,)), (3, (-2,))):
        with pytest.raises(ValueError) as ours:
            streams.stream(seed, *key)
        with pytest.raises(ValueError) as theirs:
            reference(seed, key)
        assert str(ours.value) == str(theirs.value)


def test_a_numpy_that_seeds_otherwise_is_caught_at_the_start(monkeypatch):
    """The start-up check compares the block path with SeedSequence: words that differ (a
    numpy whose SeedSequence changed) send every stream to SeedSequence itself."""
    monkeypatch.setattr(streams, "_checked", [])
    monkeypatch.setattr(streams, "_blocks", {})
    real = streams.seed_words
    monkeypatch.setattr(streams, "seed_words", lambda seed, keys: real(seed, keys) ^ np.uint64(1))
    assert same(streams.stream(2026, 2, 5, 77), reference(2026, (2, 5, 77)))
    assert streams._checked == [False] and streams._blocks == {}


def test_blocks_kept_are_bounded(monkeypatch):
    monkeypatch.setattr(streams, "_blocks", {})
    monkeypatch.setattr(streams, "BLOCKS_KEPT", 8)
    for j in range(20):
        streams.sensor_stream(1, j, 3)
    assert len(streams._blocks) == 8
    assert (1, (streams.SENSOR, 19), 0) in streams._blocks  # the newest stay
    assert same(streams.sensor_stream(1, 0, 3), reference(1, (streams.SENSOR, 0, 3)))


def test_a_generator_asks_only_for_its_words_else_the_real_sequence_answers():
    w = streams._Words(streams.seed_words(9, [[1, 2]])[0], 9, (1, 2))
    real = np.random.SeedSequence(9, spawn_key=(1, 2))
    assert np.array_equal(w.generate_state(4, np.uint64), real.generate_state(4, np.uint64))
    assert np.array_equal(w.generate_state(8), real.generate_state(8))
    assert np.array_equal(w.generate_state(2, np.uint64), real.generate_state(2, np.uint64))
    first = w.generate_state(4, np.uint64)
    first[0] = 0  # a caller's copy: the block stays as it was
    assert np.array_equal(w.generate_state(4, np.uint64), real.generate_state(4, np.uint64))
