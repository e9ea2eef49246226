"""Per-scan rows off the heap: the mobile manager's (as Python lists of arrays they grew the
manager by about 2 kB a scan, +13 % over 5 000 scans) in spilling columns, read back bit for bit
as ``np.array(rows, dtype)`` gave them (a None of a float row is NaN there and here); the
passive manager's records as JSON lines."""

from __future__ import annotations

import numpy as np

from covnet.mobile.network import ScanRows
from covnet.runs.columns import BLOCK


def test_the_rows_read_back_as_np_array_of_the_lists_did():
    rng = np.random.default_rng(3)
    rows, lists = ScanRows(), {"x_est": [], "modes": [], "detected": [], "J_star": []}
    for k in range(BLOCK + 37):
        values = {
            "x_est": rng.normal(size=(3, 4)),
            "modes": rng.integers(0, 4, size=5),
            "detected": rng.random(3) < 0.5,
            "J_star": None if k % 7 == 0 else float(rng.normal()),
        }
        for name, v in values.items():
            rows.append(name, v)
            lists[name].append(v)
    for name, dtype in (("x_est", float), ("modes", np.int64), ("detected", bool)):
        want = np.array(lists[name], dtype=dtype)
        got = rows.array(name)
        assert got.dtype == want.dtype and np.array_equal(got, want), name
    want = np.array(lists["J_star"], dtype=np.float64)
    assert np.array_equal(rows.array("J_star"), want, equal_nan=True)
    assert np.isnan(rows.array("J_star")[0])
    assert rows.count("modes") == BLOCK + 37 and rows.count("usage") == 0
    assert rows.array("usage").shape == (0,)
    assert rows._cols["x_est"]._spilled == BLOCK  # the first block is off the heap


def test_records_spill_and_read_back_as_their_json():
    """The passive manager's per-scan records (every scan's lists, for association.json) grew
    it by 9 kB a scan; kept as :class:`Records` they spill as JSON lines and read back as the
    same JSON (a tuple a list, as json.dumps writes it)."""
    import json

    from covnet.runs.columns import Records

    rng = np.random.default_rng(1)
    recs, want = Records(), []
    for k in range(BLOCK + 5):
        r = {"scan": k, "ok": bool(k % 3), "triples": [(1, 2, 3)] * (k % 4),
             "cost": float(rng.normal()) if k % 5 else None, "nan": float("nan")}  # fmt: skip
        recs.append(r)
        want.append(r)
    assert recs._spill is not None and len(recs._tail) == 5 and len(recs) == BLOCK + 5
    got = recs.list()
    assert json.dumps(got) == json.dumps(want)
    assert got[7]["triples"] == [[1, 2, 3]] * 3
