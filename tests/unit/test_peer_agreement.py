"""A peer network's ``agreement``: over every scan the nodes reported.  A node frozen for 1.5 s
missed one scan's Status, was left out by the others and went on alone, disagreeing at 258 of
300 scans, while ``summary.json`` said ``agreement: true``: each node's run stops at its first
gap, and the runs were compared only that far."""

from __future__ import annotations

import json

import numpy as np

from covnet.covariance_control.config import load
from covnet.covariance_control.peer_run import NodeLog, PeerResult, disagreement, write_peer_run
from covnet.processes.runtime_stats import NetStats
from covnet.wire import messages as msg


def _log(enabled_by_scan: dict[int, tuple[str, ...]]) -> NodeLog:
    log = NodeLog()
    for k, enabled in enabled_by_scan.items():
        log.add(msg.Status(k, float(k), enabled, 1.0, 1.0, 1.0, 0))
        log.add(msg.Track(k, float(k), np.zeros(4), np.eye(4) * 10.0, 0))
    return log


def test_a_gap_and_a_node_going_on_alone_are_disagreements():
    all_ = {k: ("S1", "S2") for k in range(1, 7)}
    alone = {k: (("S1", "S2") if k < 3 else ("S3",)) for k in (1, 2, 4, 5, 6)}  # no scan 3
    logs = {"S1": _log(all_), "S2": _log(all_), "S3": _log(alone)}
    assert disagreement(logs) == [3, 4, 5, 6]
    assert disagreement({"S1": _log(all_), "S2": _log(all_)}) == []
    # a node that stops (killed) is not a disagreement after its last report
    assert disagreement({"S1": _log(all_), "S3": _log({1: ("S1", "S2"), 2: ("S1", "S2")})}) == []


def test_the_summary_says_the_nodes_disagree(paper_path, tmp_path):
    sc = load(paper_path)
    ids = sc.sensor_ids
    every = {k: ids[:4] for k in range(1, 7)}
    alone = {k: (ids[:4] if k < 3 else ids[4:]) for k in (1, 2, 4, 5, 6)}
    logs = {n: _log(alone if n == "S8" else every) for n in ids}
    result = PeerResult(["spectral"], {0: logs}, NetStats(), completed=True)
    write_peer_run(tmp_path, sc, result)
    peer = json.loads((tmp_path / "summary.json").read_text())["peer"]["spectral"]
    assert peer["agreement"] is False and peer["disagree_scans"] == [3, 4, 5, 6]


def test_what_the_nodes_do_not_report_is_null_not_zero(paper_path, tmp_path):
    """A node's Status does not carry how many subsets it evaluated: the network peer run's
    summary said 0 (``covnet run --fusion peer``: 255)."""
    sc = load(paper_path)
    logs = {n: _log({k: sc.sensor_ids[:4] for k in (1, 2, 3)}) for n in sc.sensor_ids}
    write_peer_run(tmp_path, sc, PeerResult(["spectral"], {0: logs}, NetStats(), completed=True))
    blk = json.loads((tmp_path / "summary.json").read_text())["metrics"]["spectral"]
    assert blk["subsets_evaluated_median"] is None


def test_a_node_log_keeps_its_rows_off_the_heap_and_reads_back_every_report():
    """The peer monitor kept every node's decoded Track and Status (17 kB a scan for 8 nodes):
    a NodeLog keeps rows in a spilling column and the latest Statuses whole; what it reads
    back is what was added (a later report of a scan replacing an earlier one)."""
    from covnet.runs.columns import BLOCK

    rng = np.random.default_rng(7)
    log, want_s, want_t = NodeLog(), {}, {}
    ids = ("S1", "S2", "S3")
    for k in [*range(1, 2 * BLOCK + 10), 5, 17]:  # two scans reported again
        st = msg.Status(
            k, float(k), tuple(i for i in ids if rng.random() < 0.5), 1.0, 1.0,
            float(rng.normal()), 0, failed=tuple(i for i in ids if rng.random() < 0.1),
        )  # fmt: skip
        A = rng.normal(size=(4, 4))
        tr = msg.Track(k, float(k), rng.normal(size=4), A @ A.T + np.eye(4), 0)
        log.add(st)
        log.add(tr)
        want_s[k], want_t[k] = st, tr
    assert log._rows._spilled > 0 and len(log._recent) <= 64  # the heap holds one block
    assert set(log.statuses) == set(want_s) and set(log.tracks) == set(want_t)
    for k, st in want_s.items():
        got = log.statuses[k]
        assert (got.enabled, got.value, got.failed) == (st.enabled, st.value, st.failed)
        assert np.array_equal(log.tracks[k].x, want_t[k].x)
        assert np.array_equal(log.tracks[k].P, want_t[k].P)
    assert log.scans() == 2 * BLOCK + 9
    assert log.has_status(2 * BLOCK + 9) and log.has_status(3) and not log.has_status(10**6)
    assert log.recent_status(2 * BLOCK + 9) is want_s[2 * BLOCK + 9]
