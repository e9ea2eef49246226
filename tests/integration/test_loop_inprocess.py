"""World, sensor and manager loops in threads over one InMemoryHub: the distributed protocol
without processes.  It must reproduce ``covnet run`` exactly (same functions, same streams)."""

from __future__ import annotations

import json
import threading

import numpy as np
import pytest
from nodethreads import with_metrics

from covnet.clock import WallClock
from covnet.covariance_control.config import with_overrides
from covnet.covariance_control.simulate import run_metric
from covnet.wire import messages as msg
from covnet.wire.bus import InMemoryBus, InMemoryHub
from manager import covariance as manager_node
from sensors import covariance as sensor_node
from world import covariance as world_node


def run_network(sc, metrics, *, kill_after_scan=None, victim=None, act=None):
    hub = InMemoryHub()
    stop = threading.Event()
    node_stops = {}
    threads = []
    stats = {}

    def start(name, target, *args):
        ev = threading.Event()
        node_stops[name] = ev
        bus = InMemoryBus(hub, name=name)

        def body():
            try:
                stats[name] = target(*args, bus, "t", WallClock(), ev)
            finally:
                bus.close()

        th = threading.Thread(target=body, name=name, daemon=True)
        th.start()
        threads.append(th)

    start("world", world_node.run, sc)
    for sid in sc.sensor_ids:
        start(
            sid,
            lambda sc_, bus, run, clock, ev, sid=sid: sensor_node.run(
                sc_, sid, bus, run, clock, ev
            ),
            sc,
        )

    def on_status(st):
        if kill_after_scan is not None and st["scan"] == kill_after_scan:
            node_stops[victim].set()
            # wait until it has stopped: a sensor no scan enables sees its stop event only at its
            # next heartbeat wait (nothing else wakes it), and this run is faster than that
            next(th for th in threads if th.name == victim).join(10)
        if act is not None:
            act(st, start, node_stops, threads)

    mbus = InMemoryBus(hub, name="manager")
    try:
        result = manager_node.run(
            with_metrics(sc, metrics), mbus, "t", WallClock(), stop, on_status=on_status
        )
    finally:
        for ev in node_stops.values():
            ev.set()
        for th in threads:
            th.join(timeout=10)
        mbus.close()
    return result, stats


def assert_equals_run(result, sc, metrics):
    """The network's run is ``covnet run``'s, bit for bit, for every metric."""
    assert result.completed and result.error is None
    for m in metrics:
        ref = run_metric(sc, m)
        got = result.episodes[m].as_run(len(sc.sensor_ids))
        np.testing.assert_array_equal(got.enabled, ref.enabled)
        np.testing.assert_array_equal(got.x_est, ref.x_est)
        np.testing.assert_array_equal(got.P_post, ref.P_post)


@pytest.fixture(scope="module")
def short_paper(paper):
    net = paper.network.model_dump() | {"record": False}
    return with_overrides(paper, scans=30, network=net)


def test_in_process_network_equals_run(short_paper):
    metrics = ["spectral", "svd"]
    result, stats = run_network(short_paper, metrics)
    assert_equals_run(result, short_paper, metrics)
    # obedience: each sensor measured exactly in the scans it was enabled
    for j, sid in enumerate(short_paper.sensor_ids):
        enabled = sum(int(result.episodes[m].as_run(8).enabled[:, j].sum()) for m in metrics)
        assert stats[sid].measurements_sent == enabled == stats[sid].enabled_scans
        assert stats[sid].commands == enabled  # the others were never delivered to it
    assert result.stats.rejected == {}
    assert result.stats.lost == 0


@pytest.mark.parametrize("upfront_max", [5000, 10])
def test_truth_up_front_and_window_by_window_give_the_run(short_paper, monkeypatch, upfront_max):
    """A short run gets all its truth at once (the world hears no command); a longer one
    (here: a 10-scan limit against 30 scans) window by window, paced by the commands, again for
    the second metric's episode. Both reproduce ``covnet run``."""
    from covnet.wire import messages as msg

    monkeypatch.setattr(msg, "TRUTH_UPFRONT_MAX_SCANS", upfront_max)
    metrics = ["abs_trace", "spectral"]
    result, stats = run_network(short_paper, metrics)
    assert_equals_run(result, short_paper, metrics)
    world = stats["world"]
    if upfront_max >= short_paper.scans:
        assert world["published"] == short_paper.scans  # once, for both episodes
    else:
        # each scan's truth once an episode (each window's last scan went out twice: 17
        # truths a 16 scans)
        assert world["published"] == 2 * short_paper.scans
    assert all(stats[sid].missed_truth == 0 for sid in short_paper.sensor_ids)


def test_a_world_restarted_with_a_command_in_flight_sends_that_scans_truth(
    short_paper, monkeypatch
):
    """Truth window by window (a run above TRUTH_UPFRONT_MAX_SCANS, here 10): the world died
    and came back while Command(18) was in flight, past its last window (scans 1-17 went out
    with Command(1)).  The new world waited for the next command, its sensors for scan 18's
    truth: that scan waited scan_timeout_s and fused nothing.  Until its first command the
    world now follows the sensors' heartbeats (the last command each took)."""
    from covnet.wire import messages as msg

    monkeypatch.setattr(msg, "TRUTH_UPFRONT_MAX_SCANS", 10)

    def restart(st, start, node_stops, threads):
        if st["scan"] == 8 and not node_stops["world"].is_set():
            node_stops["world"].set()
            next(th for th in threads if th.name == "world").join(10)
        if st["scan"] == 17 and "world-2" not in node_stops:
            # Command(18) is out (it goes before scan 17's report): the new world missed it
            start("world-2", world_node.run, short_paper)

    metrics = ["spectral"]
    result, stats = run_network(short_paper, metrics, act=restart)
    assert_equals_run(result, short_paper, metrics)
    assert stats["world-2"]["published"] >= 30 - 18 + 1


def test_lockstep_with_slow_links_does_not_wait_for_the_deadline(short_paper):
    """Lockstep with slow links (--netns: the delays on real paths): every scan waited its
    whole scan_timeout_s (10 s on a 20 ms link) after every sensor had answered, collecting to
    a deadline that only real time has (in lockstep nothing is late)."""
    net = short_paper.network.model_dump() | {
        "scan_timeout_s": 3.0,
        "latency": {"uplink": {"delay": {"kind": "constant", "value_s": 0.02}}, "late": "oosm"},
    }
    sc = with_overrides(short_paper, scans=4, network=net)
    result, _ = run_network(sc, ["spectral"])
    assert result.completed and result.error is None
    waits = np.array(result.stats.scan_latency_ns) / 1e9
    assert len(waits) == 4 and waits.max() < sc.network.scan_timeout_s / 2, waits


def test_failed_sensor_is_excluded_and_run_completes(short_paper):
    sc = with_overrides(short_paper, scans=20)
    # S2 is used by spectral at scan 1; stop it after scan 3
    result, _ = run_network(sc, ["spectral"], kill_after_scan=3, victim="S2")
    assert result.completed
    en = result.episodes["spectral"].as_run(8).enabled
    assert not en[4:, 1].any()  # never enabled again once seen failed
    events = result.episodes["spectral"].failures
    assert events and events[0]["sensor"] == "S2" and events[0]["event"] == "failed"
    assert events[0]["scan"] <= 5


def test_a_sensor_failure_is_counted_once_whatever_the_number_of_metrics(short_paper):
    """Each metric's episode starts its failure log afresh, so one failure is an event of every
    episode; ``membership`` (run.json, network.json) counted it once an episode (one SIGKILL:
    ``failed: 3`` with three metrics)."""
    sc = with_overrides(short_paper, scans=12)
    metrics = ["spectral", "trace_diff"]
    result, _ = run_network(sc, metrics, kill_after_scan=3, victim="S2")
    assert result.completed
    assert all(
        [ev["event"] for ev in result.episodes[m].failures if ev["sensor"] == "S2"] == ["failed"]
        for m in metrics
    )  # every episode's log has it
    assert result.stats.membership_counts() == {"S2": {"failed": 1, "rejoined": 0}}


def test_when_every_sensor_has_failed_the_scans_go_on_predicting(paper):
    """Every sensor down at once (the one host of all of them killed): the manager died with
    "all 8 sensors are excluded, so no non-empty subset is feasible" (exit 1, even under
    ``restart: on-failure``).  A scan with nobody alive enables nobody and only predicts."""
    from covnet.core.metrics import get_metric
    from covnet.covariance_control.config import from_dict, normalised
    from covnet.covariance_control.model import build_model

    data = normalised(paper)
    data.update(scans=10, sensors=data["sensors"][:1])
    data["network"]["record"] = False
    sc = from_dict(data)
    result, _ = run_network(sc, ["spectral"], kill_after_scan=3, victim="S1")
    assert result.completed and result.error is None
    run = result.episodes["spectral"].as_run(1)
    (event,) = result.episodes["spectral"].failures
    k = event["scan"]
    assert event["event"] == "failed" and k <= 6
    assert run.enabled[: k - 1].any() and not run.enabled[k - 1 :].any()
    np.testing.assert_array_equal(run.P_post[k - 1 :], run.P_pred[k - 1 :])  # predict only
    f, model = get_metric("spectral"), build_model(sc)
    for i in range(k - 1, sc.scans):
        assert run.value[i] == f(run.P_pred[i], model.desired(i + 1))


class _OlderNode:
    """A node's bus whose heartbeats name no config: a covnet from before heartbeats named it."""

    def __init__(self, bus):
        self.bus = bus

    def __getattr__(self, name):
        return getattr(self.bus, name)

    def publish(self, key, payload):
        if "/hb/" in key:
            payload = msg.encode(msg.decode_as(payload, msg.Heartbeat).evolve(config=None))
        return self.bus.publish(key, payload)


def test_a_node_that_names_no_config_is_refused_by_name(short_paper):
    """A sensor of an older covnet (no ``config`` in its heartbeats: its seed and config cannot
    be checked) was let in; a host of the Dec 5 code with another seed ran one mixed network
    that ended ``completed``, exit 0 (hunt 14).  The manager refuses to start and names it."""
    hub = InMemoryHub()
    stops = []
    threads = []

    def start(name, target, wrap=None):
        ev = threading.Event()
        stops.append(ev)
        bus = InMemoryBus(hub, name=name)
        th = threading.Thread(
            target=lambda: target(wrap(bus) if wrap else bus, ev), name=name, daemon=True
        )
        th.start()
        threads.append((th, bus))

    sc = with_overrides(short_paper, network={**short_paper.network.model_dump(),
                                               "ready_timeout_s": 10.0})  # fmt: skip
    start("world", lambda bus, ev: world_node.run(sc, bus, "t", WallClock(), ev))
    for sid in sc.sensor_ids:
        wrap = _OlderNode if sid == "S3" else None
        start(
            sid, lambda bus, ev, sid=sid: sensor_node.run(sc, sid, bus, "t", WallClock(), ev), wrap
        )
    mbus = InMemoryBus(hub, name="manager")
    try:
        result = manager_node.run(sc, mbus, "t", WallClock(), threading.Event())
    finally:
        for ev in stops:
            ev.set()
        for th, bus in threads:
            th.join(timeout=10)
            bus.close()
        mbus.close()
    assert not result.completed and result.error is not None
    assert "nodes name no config in their heartbeats: S3 (an older covnet" in result.error
    assert "another config" not in result.error  # the others run this one


class _RestartedWithAnotherConfig:
    """S3's bus: after its ``after``-th measurement the node "restarts" with another config
    file (``restart: on-failure`` reads the file again): a heartbeat naming another config,
    then its measurements as before."""

    def __init__(self, bus, after):
        self.bus, self.after, self.sent, self.said = bus, after, 0, False

    def __getattr__(self, name):
        return getattr(self.bus, name)

    def publish(self, key, payload):
        if "/meas" in key:
            self.sent += 1
            if self.sent > self.after and not self.said:
                self.said = msg.decode_as(payload, msg.Measurement).scan
                hb = msg.Heartbeat(role="sensor", node_id="S3", scan=0, t_sent_ns=1,
                                   config="0123456789abcdef")  # fmt: skip
                self.bus.publish(msg.heartbeat_key("t", "sensor", "S3"), msg.encode(hb))
        return self.bus.publish(key, payload)


def test_a_node_that_comes_back_with_another_config_is_kept_out(short_paper, tmp_path):
    """A sensor restarted mid-run with an edited config file: the manager refused its
    heartbeats (``config_mismatch``) but took its measurements as signs of life, so it
    "rejoined" and was fused at every scan to the end, ``completed``, exit 0 (hunt 14).  It is
    down from its first heartbeat of another config on, and nothing it sends is fused."""
    from nodethreads import run_recorded_network

    from covnet.covariance_control.replay import RECORDING
    from covnet.runs.recording import read_recording
    from manager.process import config_refused

    out = tmp_path / "run"
    s3 = []

    def restarted(bus):
        s3.append(_RestartedWithAnotherConfig(bus, 1))
        return s3[0]

    result, _ = run_recorded_network(short_paper, ["spectral"], out, wrap_bus={"S3": restarted})
    assert result.completed
    k0 = s3[0].said  # the scan whose measurement followed the heartbeat (taken, or not, by
    assert k0  # the race of two subscriptions): from the next scan on, S3 is out
    fused = {}
    for s in read_recording(out / RECORDING):
        m = msg.decode(s.payload)
        if isinstance(m, msg.Status):
            fused[m.scan] = "S3" in m.fused
    assert any(fused[k] for k in fused if k < k0), fused  # it was used before
    assert not any(fused[k] for k in fused if k > k0), fused
    failures = json.loads((out / "summary.json").read_text())["failures"]["spectral"]
    assert [(f["sensor"], f["event"]) for f in failures] == [("S3", "failed")], failures
    rejected = result.stats.rejected_by_key
    assert rejected[msg.heartbeat_key("t", "sensor", "S3")]["config_mismatch"] == 1
    (note,) = config_refused(rejected)
    assert note.endswith("S3 ran another config than this run's from some point on (1 "
                         "heartbeat(s) refused; was it restarted after the config file was "
                         "edited?): it was kept out of the allocation and nothing it sent was "
                         "fused")  # fmt: skip
