"""``covnet.runs.columns.Column`` holds exactly what a list of rows would (bit for bit)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from covnet.runs.columns import BLOCK, Column


@settings(max_examples=30, deadline=None)
@given(
    n=st.sampled_from([0, 1, BLOCK - 1, BLOCK, BLOCK + 1, 2 * BLOCK + 7]),
    shape=st.sampled_from([(), (3,), (4, 4)]),
    seed=st.integers(0, 2**32 - 1),
)
def test_a_column_stacks_its_rows_as_np_array_would(n, shape, seed):
    rng = np.random.default_rng(seed)
    rows = [rng.standard_normal(shape) for _ in range(n)]
    col = Column(shape)
    for r in rows:
        col.append(r)
    want = np.array(rows, dtype=np.float64).reshape(n, *shape)
    got = col.array()
    assert got.shape == want.shape and got.dtype == want.dtype
    assert got.tobytes() == want.tobytes()
    assert len(col) == n and bool(col) == (n > 0)
    assert all(np.array_equal(a, b) for a, b in zip(col, rows, strict=True))


def test_bool_and_int_columns_cast_like_np_array():
    masks = Column((3,), bool)
    ints = Column((), np.int64)
    for i in range(5):
        masks.append(np.array([i % 2 == 0, True, False]))
        ints.append(i * 7)
    assert masks.array().tolist() == [[i % 2 == 0, True, False] for i in range(5)]
    assert ints.array().dtype == np.int64 and ints.array().tolist() == [0, 7, 14, 21, 28]


def test_a_column_whose_init_was_cut_short_is_collected_quietly(monkeypatch):
    """A Ctrl-C inside ``Column.__init__`` (seen in the suite: ``covnet run`` interrupted while
    its forks start) left an instance without ``_spill``; its ``__del__`` then printed
    "Exception ignored ... AttributeError: 'Column' object has no attribute '_spill'"."""
    import gc

    import numpy as np

    from covnet.runs.columns import Column

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    seen = []
    monkeypatch.setattr("sys.unraisablehook", lambda u: seen.append(u))
    monkeypatch.setattr(np, "dtype", interrupted)
    try:
        Column((2,), np.float64)
    except KeyboardInterrupt:
        pass
    monkeypatch.undo()
    gc.collect()
    assert not seen, [str(u.exc_value) for u in seen]


def test_a_full_spill_folder_is_named(monkeypatch, tmp_path):
    """A spill file is anonymous, so its error named no file: a full ``$TMPDIR`` was a bare
    "No space left on device" while the disk of ``--out`` had room (hunt 11)."""
    import errno
    import tempfile

    from covnet.runs import columns
    from covnet.runs.rundir import os_error_text

    class Full:
        def seek(self, *a):
            return 0

        def write(self, data):
            raise OSError(errno.ENOSPC, "No space left on device")

        def close(self):
            pass

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    monkeypatch.setattr(tempfile, "TemporaryFile", lambda **kw: Full())
    for store, row in ((columns.Column((2,)), np.zeros(2)), (columns.Records(), {})):
        with pytest.raises(OSError) as err:
            for _ in range(columns.BLOCK + 1):
                store.append(row)
        text = os_error_text(err.value)
        assert str(tmp_path) in text and "No space left on device" in text and "TMPDIR" in text
        assert err.value.errno == errno.ENOSPC
