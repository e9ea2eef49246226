"""Many targets over the bus (issue 16): the world publishes every target's truth, each command
names every enabled sensor's target and clutter window, each sensor simulates its own dwell,
the manager gates, associates and fuses.  In lockstep it is ``covnet run`` bit for bit; a
killed sensor leaves the allocation; ``covnet replay`` reproduces the run."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import numpy as np
import pytest
import yaml
from nodethreads import with_metrics

from covnet.clock import WallClock
from covnet.covariance_control.config import from_dict
from covnet.covariance_control.simulate import run_targets
from covnet.wire.bus import InMemoryBus, InMemoryHub
from manager import covariance as manager_node
from sensors import covariance as sensor_node
from world import covariance as world_node

ROOT = Path(__file__).resolve().parents[2]


def short_data(scans: int = 16) -> dict:
    data = yaml.safe_load((ROOT / "configs" / "multitarget.yaml").read_text())
    data["scans"] = scans
    data["allocation"]["metrics"] = ["abs_trace", "spectral"]
    data["targets"][2]["manoeuvres"][0].update(from_scan=4, to_scan=10)
    for t in data["targets"]:
        if len(t["desired"]) > 1:
            t["desired"][1]["from_scan"] = scans // 2
    data["network"] = {"record": False}
    return data


@pytest.fixture(scope="module")
def short():
    return from_dict(short_data())


def run_network(sc, metrics, *, kill_after_scan=None, victim=None):
    hub = InMemoryHub()
    stop = threading.Event()
    node_stops, threads, stats = {}, [], {}

    def start(name, target):
        ev = threading.Event()
        node_stops[name] = ev
        bus = InMemoryBus(hub, name=name)

        def body():
            try:
                stats[name] = target(bus, ev)
            finally:
                bus.close()

        th = threading.Thread(target=body, name=name, daemon=True)
        th.start()
        threads.append(th)

    start("world", lambda bus, ev: world_node.run(sc, bus, "t", WallClock(), ev))
    for sid in sc.sensor_ids:
        start(sid, lambda bus, ev, sid=sid: sensor_node.run(sc, sid, bus, "t", WallClock(), ev))

    def on_status(st):
        if kill_after_scan is not None and st["scan"] == kill_after_scan and st["episode"] == 0:
            node_stops[victim].set()
            next(th for th in threads if th.name == victim).join(10)

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


def test_in_process_network_equals_run(short):
    metrics = ["abs_trace", "spectral"]
    result, stats = run_network(short, metrics)
    assert result.completed and result.error is None
    for m in metrics:
        ref = run_targets(short, m)
        got = result.episodes[m].as_run()
        np.testing.assert_array_equal(got.assignment, ref.assignment)
        np.testing.assert_array_equal(got.x_est, ref.x_est)
        np.testing.assert_array_equal(got.P_post, ref.P_post)
        np.testing.assert_array_equal(got.returns, ref.returns)
        np.testing.assert_array_equal(got.nis_sum, ref.nis_sum)
    for j, sid in enumerate(short.sensor_ids):
        on = sum(int(result.episodes[m].as_run().enabled[:, j].sum()) for m in metrics)
        assert stats[sid].measurements_sent == on == stats[sid].enabled_scans
    assert result.stats.rejected == {}
    assert result.stats.lost == 0


def test_a_stopped_sensor_leaves_the_allocation(short):
    """A sensor that dies is out of every assignment from the scan its failure is seen on, the
    run completes, and the scans before are ``covnet run``'s."""
    ref = run_targets(short, "abs_trace")
    counts = ref.enabled[:4].sum(axis=0)
    victim = short.sensor_ids[int(np.argmax(counts))]  # the busiest early on
    result, _ = run_network(short, ["abs_trace"], kill_after_scan=3, victim=victim)
    assert result.completed
    log = result.episodes["abs_trace"]
    fails = [ev for ev in log.failures if ev["sensor"] == victim and ev["event"] == "failed"]
    assert fails, log.failures
    first = fails[0]["scan"]
    got = log.as_run()
    j = short.sensor_ids.index(victim)
    assert first <= 5
    assert not got.enabled[first - 1 :, j].any()
    np.testing.assert_array_equal(got.assignment[:3], ref.assignment[:3])
    np.testing.assert_array_equal(got.x_est[:, :3], ref.x_est[:, :3])


@pytest.mark.integration
@pytest.mark.timeout(240)
# info over real processes under the slow marker: the suite's time (its in-memory-bus twin,
# test_info_over_the_bus_equals_run, and the central variant over real processes stay)
@pytest.mark.parametrize("fusion", ["central", pytest.param("info", marks=pytest.mark.slow)])
def test_up_equals_run_and_replays(tmp_path, fusion):
    """12 sensor processes over zenoh in lockstep: covnet run's results, and covnet replay
    reproduces the summary from the recording (returns, or local tracks under info)."""
    from multiproc import CovnetProcess, assert_nothing_left
    from traffic_check import assert_compare_counts_what_was_sent

    from covnet.cli.app import main as covnet_main
    from covnet.runs.rundir import load_arrays

    data = short_data(12)
    data["allocation"]["metrics"] = ["abs_trace"]
    data.pop("network")
    data["fusion"] = {"mode": fusion}
    cfg = tmp_path / "mt.yaml"
    cfg.write_text(yaml.safe_dump(data))
    ref = tmp_path / "ref"
    assert covnet_main(["run", str(cfg), "--out", str(ref), "--no-figures"]) == 0
    out = tmp_path / "up"
    p = CovnetProcess(["up", str(cfg), "--out", str(out), "--no-figures"])
    try:
        rc = p.wait(timeout=200)
    finally:
        p.stop()
    assert rc == 0, p.output()
    names = set(json.loads((out / "processes.json").read_text()))
    assert names == {"manager", "world", "recorder", *data_ids(data)}
    a = json.loads((ref / "summary.json").read_text())
    b = json.loads((out / "summary.json").read_text())
    assert b["completed"] is True and a["metrics"] == b["metrics"]
    ra, rb = load_arrays(ref / "arrays.npz"), load_arrays(out / "arrays.npz")
    for k in ("assignment.abs_trace", "x_est.abs_trace", "P_post.abs_trace", "ospa.abs_trace"):
        np.testing.assert_array_equal(ra[k], rb[k])
    net = json.loads((out / "network.json").read_text())
    assert net["rejected"] == {} and net["lost"] == 0
    assert_compare_counts_what_was_sent(out, fusion)  # compare --policies' bytes: the recording's
    assert_nothing_left(out)
    rp = CovnetProcess(["replay", str(out)])
    assert rp.wait(timeout=120) == 0, rp.output()
    assert "identical" in rp.output()


def data_ids(data: dict) -> set[str]:
    return {s["id"] for s in data["sensors"]}


def test_info_over_the_bus_equals_run():
    """fusion.mode info: each sensor publishes its local track of the target it dwelt on; in
    lockstep the centre's information fusion is covnet run's bit for bit."""
    sc = from_dict({**short_data(), "fusion": {"mode": "info"}})
    result, stats = run_network(sc, ["abs_trace"])
    assert result.completed and result.stats.rejected == {}
    ref = run_targets(sc, "abs_trace")
    got = result.episodes["abs_trace"].as_run()
    np.testing.assert_array_equal(got.assignment, ref.assignment)
    np.testing.assert_array_equal(got.x_est, ref.x_est)
    np.testing.assert_array_equal(got.P_post, ref.P_post)


@pytest.mark.parametrize("fusion", ["central", "info"])
def test_compare_counts_the_bytes_the_nodes_send(tmp_path, fusion):
    """``compare --policies``' messages and bytes per scan for a run's assignments are what
    the nodes published (the in-memory network with its recorder): under ``info`` each enabled
    sensor's local track, and every field as long as a real one (the count was 3-7 % short)."""
    from nodethreads import run_recorded_network
    from traffic_check import assert_compare_counts_what_was_sent

    sc = from_dict({**short_data(), "fusion": {"mode": fusion}})
    run_recorded_network(sc, ["abs_trace"], tmp_path / "run")
    assert_compare_counts_what_was_sent(tmp_path / "run", fusion)
