"""Peer nodes, the world and the peer monitor as threads over one InMemoryHub: the peer
protocol without processes reproduces the in-process peer run exactly, malformed statuses and
tracks are counted and dropped, and a stopped node drops out of every decision."""

from __future__ import annotations

import json
import threading
import time
from collections import Counter

import numpy as np
import pytest
from nodethreads import NodeThreads, with_metrics

from covnet.clock import WallClock
from covnet.covariance_control.config import from_dict, normalised
from covnet.covariance_control.decentral_sim import run_peer
from covnet.covariance_control.model import build_model
from covnet.covariance_control.peer_run import write_peer_run
from covnet.covariance_control.replay import RECORDING, replay_run
from covnet.processes.node_kit import WORLD_GONE_WAIT_S
from covnet.runs.recording import RecordingWriter, run_metadata
from covnet.wire import messages as msg
from covnet.wire.bus import InMemoryBus
from manager import peer_monitor
from manager.process import LINGER_S
from recorder import node as recorder_node
from sensors import peer
from world import covariance as world_node

pytestmark = pytest.mark.timeout(120)
RUN = "t"


def _scenario(paper, graph="ring", scans=15):
    data = normalised(paper)
    data["scans"] = scans
    data["network"]["record"] = False
    data["fusion"] = {"mode": "peer", "peer": {"graph": graph}}
    return from_dict(data)


def _network(sc, metrics, *, extra=None, stop_node=None, linger_s=0.0, act=None):
    nodes = NodeThreads()
    nodes.start("world", lambda bus, ev: world_node.run(sc, bus, RUN, WallClock(), ev))
    for sid in sc.sensor_ids:
        nodes.start(
            sid, lambda bus, ev, sid=sid: peer.run(sc, sid, metrics, bus, RUN, WallClock(), ev)
        )

    def on_status(st):
        if extra is not None:
            extra(nodes.hub, st)
        if stop_node is not None and st["scan"] == stop_node[1]:
            nodes.stop(stop_node[0])
        if act is not None:
            act(nodes, st)

    mbus = nodes.bus("monitor")
    try:
        result = peer_monitor.run(
            with_metrics(sc, metrics),
            mbus,
            RUN,
            WallClock(),
            threading.Event(),
            on_status=on_status,
            linger_s=linger_s,
        )
    finally:
        mbus.close()  # the monitor's token goes: the nodes finish on their own
        nodes.close(20.0, stop_first=False)
    return result, nodes.stats


def _rogue_at_scan_2(puts):
    """An ``extra`` for :func:`_network`: a rogue session publishes ``puts`` (key, payload)
    once, as scan 2's status is reported."""
    sent = []

    def inject(hub, st):
        if st["scan"] == 2 and not sent:
            bus = InMemoryBus(hub, name="rogue")
            for key, payload in puts:
                bus.publish(key, payload)
            bus.close()
            sent.append(True)

    return inject


def test_threads_reproduce_the_in_process_peer_run(paper):
    sc = _scenario(paper)
    result, stats = _network(sc, ["abs_trace"])
    assert result.completed and result.error is None
    ref = run_peer(sc, "abs_trace")
    truth = np.zeros((sc.scans, 4))
    model = build_model(sc)
    for sid, log in result.nodes[0].items():
        run = log.as_run("abs_trace", sc.sensor_ids, truth, model)
        np.testing.assert_array_equal(run.enabled, ref[sid].enabled)
        np.testing.assert_array_equal(run.x_est, ref[sid].x_est)
        np.testing.assert_array_equal(run.P_post, ref[sid].P_post)
        # the prediction a node does not report, rebuilt as its filter made it (the network
        # wrote NaN where covnet run wrote it)
        np.testing.assert_array_equal(run.P_pred, ref[sid].P_pred)
    assert all(stats[s].scans == sc.scans for s in sc.sensor_ids)


def test_malformed_peer_messages_are_counted_and_dropped(paper):
    sc = _scenario(paper)
    bad = [
        (msg.peer_status_key(RUN, "S1"), b"\x00garbage"),
        (
            msg.peer_status_key(RUN, "S2"),
            msg.encode(msg.Status(3, 3.0, ("S1",), 1.0, 1.0, 1.0, 1, node_id="S5")),
        ),  # the key names another node
        (
            msg.measurement_key(RUN, "S2"),
            msg.encode(msg.Measurement("S2", 3, 3.0, np.zeros((1, 2)), np.eye(2), 1)),
        ),  # a measurement where a local track belongs
        (msg.peer_track_key(RUN, "S3"), b"\x92\x01"),
    ]
    result, stats = _network(sc, ["abs_trace"], extra=_rogue_at_scan_2(bad), linger_s=20.0)
    assert result.completed
    ref = run_peer(sc, "abs_trace")
    truth = np.zeros((sc.scans, 4))
    for sid, log in result.nodes[0].items():  # nothing malformed was fused
        np.testing.assert_array_equal(
            log.as_run("abs_trace", sc.sensor_ids, truth).x_est, ref[sid].x_est
        )
    rejected = sum(sum(s.rejected.values()) for sid, s in stats.items() if sid in sc.sensor_ids)
    assert rejected >= 8  # every node saw the two bad statuses; S1 and S3 the bad track
    assert sum(result.stats.rejected.values()) >= 3
    # what each node refused reaches network.json, as with a fusion centre (the monitor read
    # no heartbeat: rejected_by_node was empty in peer mode)
    by_node = result.stats.as_dict()["rejected_by_node"]
    for sid in sc.sensor_ids:
        assert by_node.get(sid, {}) == dict(stats[sid].rejected), sid
    assert sum(map(len, by_node.values())) > 0


def test_forged_heartbeats_are_counted_and_dropped(paper):
    """Heartbeats of no node of the run, or on another node's key, are refused by reason and
    their counts never reach ``rejected_by_node``."""
    sc = _scenario(paper, scans=6)
    forged = [
        (
            msg.heartbeat_key(RUN, "sensor", "S99"),
            msg.encode(msg.Heartbeat("sensor", "S99", 1, 0, rejected={"x": 9})),
        ),
        (
            msg.heartbeat_key(RUN, "sensor", "S1"),
            msg.encode(msg.Heartbeat("sensor", "S2", 1, 0, rejected={"x": 9})),
        ),
        (msg.heartbeat_key(RUN, "sensor", "S3"), b"\x00garbage"),
    ]
    result, _ = _network(sc, ["abs_trace"], extra=_rogue_at_scan_2(forged), linger_s=20.0)
    assert result.completed
    rej = result.stats.as_dict()
    assert all("x" not in v for v in rej["rejected_by_node"].values())
    assert rej["rejected"]["unknown_node"] == 1 and rej["rejected"]["key_mismatch"] == 1
    assert sum(rej["rejected"].values()) == 3


def test_a_stopped_node_drops_out_of_every_decision(paper):
    sc = _scenario(paper, scans=30)
    result, _ = _network(sc, ["abs_trace"], stop_node=("S3", 5))
    assert result.completed
    logs = result.nodes[0]
    survivors = [s for s in sc.sensor_ids if s != "S3"]
    last = {s: max(logs[s].statuses) for s in survivors}
    assert all(v == 30 for v in last.values())
    out_from = min(k for k, st in logs["S1"].statuses.items() if "S3" in st.failed)
    for s in survivors:
        for k in range(out_from, 31):
            st = logs[s].statuses[k]
            assert "S3" in st.failed and "S3" not in st.enabled
            assert st.enabled == logs["S1"].statuses[k].enabled  # all agree


def _far_track(sid, scan, episode=0):
    """A well-formed local track of ``sid`` 140 km from the target."""
    x = np.array([1e5, 0.0, 1e5, 0.0])
    return msg.encode(
        msg.LocalTrack(sid, scan, float(scan), x, np.eye(4), x, 2.0 * np.eye(4), 1, episode)
    )


def test_well_formed_tracks_of_other_scans_or_outside_the_gate_are_not_fused(paper):
    """A peer node kept any well-formed track whatever its scan, the first one of a (node,
    scan) winning: a rogue's tracks for later scans were fused and the genuine ones refused
    as duplicates (a node 140 km off, 'nodes agree: yes').  Now a track or status beyond the
    next scan is ``wrong_scan``, outside the run ``bad_scan``, and a track of the scan that
    fails the node's validation gate ``outside_gate``: the genuine one is fused."""
    sc = _scenario(paper, scans=12)
    forged = []
    for sid in sc.sensor_ids:
        key = msg.measurement_key(RUN, sid)
        forged += [(key, _far_track(sid, k)) for k in (3, 4, 8, 12)]  # near and far scans
        forged += [(key, _far_track(sid, 10**9)), (key, _far_track(sid, 3, episode=7))]
    forged.append(
        (
            msg.peer_status_key(RUN, "S1"),
            msg.encode(msg.Status(11, 11.0, ("S1",), 1.0, 1.0, 1.0, 1, node_id="S1")),
        )
    )
    far_truth = msg.Truth(10**9, 1.0, ("T1",), np.zeros((1, 4)))
    forged.append((msg.truth_key(RUN), msg.encode(far_truth)))
    result, stats = _network(sc, ["abs_trace"], extra=_rogue_at_scan_2(forged), linger_s=20.0)
    assert result.completed
    ref = run_peer(sc, "abs_trace")
    truth = np.zeros((sc.scans, 4))
    for sid, log in result.nodes[0].items():
        run = log.as_run("abs_trace", sc.sensor_ids, truth)
        np.testing.assert_array_equal(run.x_est, ref[sid].x_est)
        np.testing.assert_array_equal(run.enabled, ref[sid].enabled)
    refused = sum((stats[s].rejected for s in sc.sensor_ids), start=Counter())
    # every node hears its two ring neighbours' keys: two tracks of 10**9 and two of episode 7
    assert refused["bad_scan"] >= 4 * len(sc.sensor_ids) + len(sc.sensor_ids)  # + the truth
    assert refused["wrong_scan"] >= 2 * len(sc.sensor_ids)  # at least the scan-12 tracks
    # and every one of them is counted: the tracks of scans 3 and 4 kept as the next scan's
    # and never taken (they came after the node had fused that scan) went uncounted before
    per_node = [stats[s].rejected for s in sc.sensor_ids]
    for s, r in zip(sc.sensor_ids, per_node, strict=True):
        counted = r["outside_gate"] + r["wrong_scan"] + r["late"] + r["not_enabled"]
        assert counted >= 2 * 4, (s, dict(r))  # two neighbours' keys, scans 3, 4, 8 and 12


def test_failures_are_the_majority_view():
    """A node frozen for seconds found none of its peers' statuses and left them all out:
    merged, every node's view made every sensor "failed" (summary.json listed all eight).
    A node is failed where most of the others that reported the scan say so."""
    from types import SimpleNamespace as S

    from covnet.covariance_control.peer_run import failed_by_majority

    ids = [f"S{i}" for i in range(1, 6)]

    def st(failed):
        return S(failed=tuple(failed))

    statuses = {n: {k: st([]) for k in range(1, 4)} for n in ids}
    for n in ids[:4]:  # S5 frozen after scan 1: the others leave it out from scan 2
        statuses[n].update({2: st(["S5"]), 3: st(["S5"])})
    statuses["S5"][3] = st(ids[:4])  # and it, back, leaves them all out
    assert failed_by_majority(statuses) == {"S5": 2}
    statuses["S3"].pop(3)  # S3 killed after scan 2: the survivors name it at scan 3
    for n in ("S1", "S2", "S4"):
        statuses[n][3] = st(["S5", "S3"])
    assert failed_by_majority(statuses) == {"S5": 2, "S3": 3}


def _statuses_of(sub, seen):
    """Take what ``sub`` (the nodes' Status keys) holds into ``seen``: (node, scan) pairs."""
    while (s := sub.try_recv()) is not None:
        st = msg.decode_as(s.payload, msg.Status)
        seen.add((st.node_id, st.scan))


def test_a_stopped_observer_keeps_every_scan_the_nodes_reported_and_replays(paper, tmp_path):
    """Ctrl-C to ``covnet up --fusion peer``: the observer stopped taking the nodes' reports at
    once, while the nodes, which do not wait for it, had reported more scans, all recorded:
    ``covnet replay`` rebuilt those and said DIFFERS (scans_completed 49 != 50).  Here the
    observer is stopped with every node three scans ahead of what it has taken (the moment
    is made, not waited for), and the nodes and the recorder with it: it keeps every scan each
    node reported, no node is called failed, and the replay reproduces summary.json."""
    data = normalised(paper)
    data["scans"] = 40
    data["fusion"] = {"mode": "peer", "peer": {"graph": "full"}}
    sc = with_metrics(from_dict(data), ["abs_trace"])
    assert sc.network.record
    nodes = NodeThreads()
    probe = nodes.bus("probe")
    status_sub = probe.subscribe(msg.peer_keyexpr(RUN, "status"))
    writer = RecordingWriter(tmp_path / RECORDING, run_id=RUN, metadata=run_metadata(RUN, sc))
    clock = WallClock()
    nodes.start("recorder", lambda bus, ev: recorder_node.run(sc, bus, RUN, clock, ev, writer))
    nodes.start("world", lambda bus, ev: world_node.run(sc, bus, RUN, clock, ev))
    for sid in sc.sensor_ids:
        nodes.start(
            sid, lambda bus, ev, sid=sid: peer.run(sc, sid, ["abs_trace"], bus, RUN, clock, ev)
        )
    stop = threading.Event()
    seen: set[tuple[str, int]] = set()
    ahead = []

    def on_progress(result, last):
        if stop.is_set():
            return
        taken = max(max(log.statuses) for log in result.nodes[0].values() if log.statuses)
        if taken < 3:
            return
        target = taken + 3  # every node reports it before the observer takes anything more
        deadline = time.monotonic() + 30
        while not all((sid, target) in seen for sid in sc.sensor_ids):
            assert time.monotonic() < deadline, f"the nodes never reported scan {target}"
            _statuses_of(status_sub, seen)
            time.sleep(0.001)
        ahead.append((taken, target))
        stop.set()  # Ctrl-C: the observer, every node and the recorder at once
        for ev in nodes.stops.values():
            ev.set()

    mbus = nodes.bus("manager")
    try:
        result = peer_monitor.run(
            sc, mbus, RUN, clock, stop, on_progress=on_progress, linger_s=LINGER_S
        )
    finally:
        mbus.close()
        nodes.close(20.0)
        writer.close()
        probe.close()
    assert ahead, "the observer was never stopped"
    taken, target = ahead[0]
    assert not result.completed
    logs = result.nodes[0]
    for sid in sc.sensor_ids:  # every scan a node published, none cut by the stop
        assert logs[sid].scans() == nodes.stats[sid].scans >= target, (sid, ahead)
        assert max(logs[sid].statuses) == nodes.stats[sid].scans, sid
    write_peer_run(tmp_path, sc, result, {"episodes": ["abs_trace"], "run_id": RUN})
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["failures"] == {"abs_trace": []}
    info = json.loads((tmp_path / "run.json").read_text())
    assert info["scans_completed"] == summary["scans_completed"], info
    assert info["scans_completed"]["abs_trace"] >= target
    report = replay_run(tmp_path)
    assert report.identical, report.differences


def test_a_node_stopped_while_it_waits_publishes_nothing_of_that_scan(paper):
    """A node stopped (Ctrl-C) while it waited for its peers published the scan all the same,
    fused from what had come (and, cut while waiting for their statuses, naming those it had
    not heard failed): an interrupted run's last scan said sensors failed that were only
    leaving.  Here S2 is up but mute, so every other
    node waits for its scan-1 track (``scan_timeout_s`` 60 s); stopped there, none publishes
    a Track or Status."""
    data = normalised(paper)
    data["scans"] = 10
    data["network"]["record"] = False
    data["network"]["scan_timeout_s"] = 60.0
    data["fusion"] = {"mode": "peer", "peer": {"graph": "full"}}
    sc = with_metrics(from_dict(data), ["spectral"])  # scan 1 enables all eight
    nodes = NodeThreads()
    probe = nodes.bus("probe")
    sub = probe.subscribe(msg.peer_keyexpr(RUN, "*"))
    tracks = probe.subscribe(msg.measurement_keyexpr(RUN))
    tokens = [  # the mute S2 and a monitor that watches nothing
        probe.declare_token(msg.alive_key(RUN, "sensor", "S2")),
        probe.declare_token(msg.alive_key(RUN, "manager", "manager")),
    ]
    nodes.start("world", lambda bus, ev: world_node.run(sc, bus, RUN, WallClock(), ev))
    waiting = [s for s in sc.sensor_ids if s != "S2"]
    for sid in waiting:
        nodes.start(
            sid, lambda bus, ev, sid=sid: peer.run(sc, sid, ["spectral"], bus, RUN, WallClock(), ev)
        )
    try:
        sent: set[str] = set()  # a node sends its local track, then waits for S2's
        deadline = time.monotonic() + 60
        while sent != set(waiting):
            assert time.monotonic() < deadline, f"local tracks of scan 1 from {sorted(sent)} only"
            if (s := tracks.recv(timeout=0.1)) is not None:
                sent.add(msg.decode_as(s.payload, msg.LocalTrack).sensor_id)
        assert sub.try_recv() is None  # all wait: S2's track never comes
    finally:
        nodes.close(20.0)  # the stop, while they wait
        for t in tokens:
            t.undeclare()
    assert all(not th.is_alive() for th in nodes.threads)
    published = []
    while (s := sub.try_recv()) is not None:
        published.append(s.key)
    probe.close()
    assert published == [], published
    assert all(nodes.stats[sid].scans == 0 for sid in waiting)


@pytest.mark.timeout(90)
def test_a_dead_world_neither_stalls_the_nodes_nor_splits_them(paper, tmp_path):
    """The world died (not restarted): each node waited scan_timeout_s (10 s) for a truth that
    never came, then for the tracks the others could not make, and the nodes timed each other
    out at different moments and disagreed for the rest of the run.  Once the world is gone
    the waits end after node_kit.WORLD_GONE_WAIT_S: every node publishes its Status at once."""
    sc = _scenario(paper, scans=24)  # truth goes out 16 scans ahead: scans 18-24 have none
    t0 = time.monotonic()
    seen: dict[int, float] = {}
    result, _ = _network(
        sc,
        ["spectral"],
        stop_node=("world", 3),
        act=lambda nodes, st: seen.setdefault(st["scan"], time.monotonic()),
    )
    assert result.completed and result.error is None
    assert time.monotonic() - t0 < 45  # 7 scans without truth: 70-140 s before
    # one WORLD_GONE_WAIT_S a scan without truth, not two (one for the truth, then a fresh one
    # for the neighbours' tracks: 1 s a scan, hunt 12); the bound leaves 0.4 s of load a scan
    per_scan = [seen[k + 1] - seen[k] for k in range(18, 24)]
    assert sorted(per_scan)[len(per_scan) // 2] < 2 * WORLD_GONE_WAIT_S - 0.1, per_scan
    summary = write_peer_run(tmp_path, sc, result)
    assert summary["scans_completed"] == {"spectral": 24}
    peer = summary["peer"]["spectral"]
    assert peer["agreement"] is True, peer["disagree_scans"]
    assert summary["failures"]["spectral"] == []  # no live node taken for failed


@pytest.mark.timeout(90)
def test_a_world_restarted_beyond_its_window_follows_the_nodes_heartbeats(paper, tmp_path):
    """The world died and came back (``restart: on-failure``) after the nodes had left the
    window of truth it had sent: the new world sent scans 1-17 again and waited for a status,
    while every node waited ``scan_timeout_s`` for scan 18's truth; that scan was fused
    without it (no node's own track).  The new world reads the heartbeats until its first
    status: it sends scan 18's truth within a heartbeat period."""
    data = normalised(_scenario(paper, scans=24))
    data["network"]["restart"] = "on-failure"
    sc = from_dict(data)
    said = []

    def restart(nodes, st):
        said.append(st["scan"])
        if st["scan"] == 12 and "world" in nodes.stops and not nodes.stops["world"].is_set():
            nodes.stop("world")
        if st["scan"] == 17 and "world-2" not in nodes.stops:  # the nodes hold truth to 17
            nodes.start(
                "world-2", lambda bus, ev: world_node.run(sc, bus, RUN, WallClock(), ev)
            )

    result, stats = _network(sc, ["spectral"], act=restart)
    assert result.completed and result.error is None
    summary = write_peer_run(tmp_path, sc, result)
    assert summary["scans_completed"] == {"spectral": 24}
    assert summary["peer"]["spectral"]["agreement"] is True
    # every scan fused the tracks its nodes made from the truth: none went without
    subsets = summary["metrics"]["spectral"]["subsets"]
    fused = [len(s) for s in subsets]
    assert all(n > 0 for n in fused), fused
    assert stats["world-2"]["published"] >= 17 + 7, stats["world-2"]


def test_a_node_forgets_the_scans_it_is_done_with():
    """A peer node kept every scan's statuses and truths for the whole run (2.3 kB a scan:
    45 MB over the soak's 20 000 scans).  After scan k of episode e it keeps the statuses and
    tracks from (e, k) on, and the truths of scans >= k and the first TRUTHS_NEAR (the next
    episode's first window may come before this episode ends)."""
    from sensors.protocol import TRUTHS_NEAR

    inbox = peer._Inbox(InMemoryBus(), RUN, "S1", ["S2"], peer.PeerStats(), 2, 300)
    for e in (0, 1):
        for k in range(1, 301):
            inbox.statuses.update({("S2", e, k), ("S3", e, k)})
            inbox.tracks[("S2", e, k)] = []
    inbox.truth.update({j: np.zeros(4) for j in range(1, 301)})
    same = inbox.statuses
    inbox.forget_before(0, 200)
    assert inbox.statuses is same  # the set a wait holds stays the one filled
    assert min(s[1:] for s in inbox.statuses) == (0, 200) and len(inbox.statuses) == 2 * 401
    assert min(k[1:] for k in inbox.tracks) == (0, 200) and len(inbox.tracks) == 401
    assert sorted(inbox.truth) == [*range(1, TRUTHS_NEAR + 1), *range(200, 301)]
    inbox.forget_before(1, 5)  # the next episode: its first window stays
    assert len(inbox.statuses) == 2 * 296 and len(inbox.tracks) == 296
    assert sorted(inbox.truth) == [*range(1, TRUTHS_NEAR + 1), *range(200, 301)]
