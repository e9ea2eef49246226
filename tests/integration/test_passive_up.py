"""``covnet up configs/passive.yaml``: three passive sensors, the world and the manager associate
the same lists as ``covnet run`` for the same seed, in threads over an in-memory bus and as real
processes over zenoh; malformed lists are rejected and counted, never associated."""

from __future__ import annotations

import json
import threading

import numpy as np
import pytest
import yaml
from multiproc import REPO, assert_nothing_left
from nodethreads import NodeThreads
from visual_check import assert_visual_channels

from covnet.cli.app import main
from covnet.clock import WallClock
from covnet.passive.associate import scan_record
from covnet.passive.config import load, with_overrides
from covnet.passive.scene import draw
from covnet.processes.node_kit import config_id
from covnet.wire import messages as msg
from manager import passive as manager_node
from sensors import passive as sensor_node
from sensors.protocol import serve
from world import passive as world_node

PASSIVE = REPO / "configs" / "passive.yaml"
# what two runs of the same lists must agree on (wall times excluded)
COMPARED = (
    "measurements triples tuples positions_km truth truth_targets correct target_of_triple "
    "score cost status"
).split()


def _cfg(scans: int, seed: int, **net):
    cfg = load(PASSIVE)
    network = cfg.network.model_dump() | {"record": False} | net
    return with_overrides(cfg, str(PASSIVE), scans=scans, seed=seed, network=network)


def _assert_same_scan(got: dict, ref: dict) -> None:
    for name in COMPARED:
        assert got[name] == ref[name], name


def _reference(cfg, k: int) -> dict:
    """Scan ``k`` associated in process (trial k - 1 of the scene draw)."""
    model = cfg.scene_model()
    scene = draw(model, cfg.seed, k - 1)
    rec, _, _ = scan_record(scene.scan, cfg.assoc_params(model), cfg.association.method, scene)
    return rec


# --------------------------------------------------------------------------------------------
# threads over one InMemoryHub
# --------------------------------------------------------------------------------------------


def run_network(cfg, sensor_runs=None, *, kill_after_scan=None, victim=None):
    """World, sensors and manager in threads; ``sensor_runs`` replaces some sensors' loops
    (``sid -> fn(bus, stop)``).  Returns the manager's result, the nodes' counters and every
    Track the manager published."""
    nodes = NodeThreads()
    sensor_runs = sensor_runs or {}
    nodes.start("world", lambda bus, ev: world_node.run(cfg, bus, "t", WallClock(), ev))
    for sid in cfg.sensor_ids:
        fn = sensor_runs.get(sid) or (
            lambda bus, ev, sid=sid: sensor_node.run(cfg, sid, bus, "t", WallClock(), ev)
        )
        nodes.start(sid, fn)
    listener = nodes.bus("listener")
    tracks = listener.subscribe(msg.track_key("t"))

    def on_status(st):
        if kill_after_scan is not None and st["scan"] == kill_after_scan:
            nodes.stop(victim)

    mbus = nodes.bus("manager")
    try:
        result = manager_node.run(
            cfg, mbus, "t", WallClock(), threading.Event(), on_status=on_status
        )
    finally:
        nodes.close()
        mbus.close()
    got = []
    while (s := tracks.try_recv()) is not None:
        got.append(msg.decode_as(s.payload, msg.Track))
    listener.close()
    return result, nodes.stats, got


class _LosesCommand:
    """A bus whose command subscription never delivers the command of scan ``lost``."""

    def __init__(self, bus, lost):
        self.bus, self.lost = bus, lost

    def __getattr__(self, name):
        return getattr(self.bus, name)

    def subscribe(self, keyexpr, *args, **kwargs):
        sub = self.bus.subscribe(keyexpr, *args, **kwargs)
        if keyexpr != msg.command_keyexpr("t"):
            return sub
        lost = self.lost

        class Sub:
            def __getattr__(self, name):
                return getattr(sub, name)

            def recv(self, timeout=None):
                s = sub.recv(timeout=timeout)
                if s is not None and msg.decode_command(s.key, s.payload).scan == lost:
                    return None  # as a timed-out wait
                return s

        return Sub()


@pytest.mark.timeout(60)
def test_a_world_that_missed_a_command_serves_the_later_ones():
    """The passive world took only the command of the scan after its last one: once one was
    lost (its session lapsed while it was paused 1.5 s), it refused every later command as
    bad_scan, and every scan to the end waited scan_timeout_s (10 s) with nothing to associate."""
    cfg = _cfg(scans=6, seed=3, scan_timeout_s=1.0)  # scan 3 waits for its truth that long
    nodes = NodeThreads()
    nodes.start(
        "world",
        lambda bus, ev: world_node.run(cfg, _LosesCommand(bus, 3), "t", WallClock(), ev),
    )
    for sid in cfg.sensor_ids:
        nodes.start(
            sid, lambda bus, ev, sid=sid: sensor_node.run(cfg, sid, bus, "t", WallClock(), ev)
        )
    mbus = nodes.bus("manager")
    try:
        result = manager_node.run(cfg, mbus, "t", WallClock(), threading.Event())
    finally:
        nodes.close()
        mbus.close()
    assert result.completed
    world = nodes.stats["world"]
    assert world["published"] == 5 and world["rejected:bad_scan"] == 0, world
    assert [r["associated"] for r in result.scans] == [True, True, False, True, True, True]


@pytest.mark.timeout(60)
def test_in_process_network_equals_run(tmp_path):
    cfg = _cfg(scans=4, seed=11)
    result, stats, tracks = run_network(cfg)
    assert result.completed and result.error is None
    assert [r["scan"] for r in result.scans] == [1, 2, 3, 4]
    for r in result.scans:
        assert r["associated"] and r["lists_from"] == list(cfg.sensor_ids)
        _assert_same_scan(r, _reference(cfg, r["scan"]))
        # one Track per associated triple: its position, named by the triple's indices
        mine = [t for t in tracks if t.scan == r["scan"]]
        assert [t.target_id for t in mine] == ["-".join(map(str, z)) for z in r["triples"]]
        for t, p in zip(mine, r["positions_km"], strict=True):
            assert t.x.tolist() == p and np.all(np.linalg.eigvalsh(t.P) > 0)
    # scan 1 is what `covnet run` associates for the same seed
    assert main(["run", str(PASSIVE), "--out", str(tmp_path / "scene"), "--seed", "11"]) == 0
    ref = json.loads((tmp_path / "scene" / "association.json").read_text())
    _assert_same_scan(result.scans.list()[0], ref)
    for sid in cfg.sensor_ids:
        assert stats[sid].measurements_sent == stats[sid].enabled_scans == cfg.scans
        assert not stats[sid].rejected
    assert result.stats.rejected == {} and result.stats.lost == 0 and result.unassociated == 0


def _bad_sensor(cfg, sid):
    """Sensor ``sid`` that, before each good list, sends malformed ones; at scan 2 it sends
    only a malformed list (the scan then cannot be associated)."""
    good = cfg.scene_model()
    j = cfg.sensor_ids.index(sid)

    def run(bus, stop):
        key = msg.measurement_key("t", sid)
        clock = WallClock()

        def meas(k, z, R=None, **kw):
            R = (
                np.diag([good.sigma_azimuth[j] ** 2, good.sigma_elevation[j] ** 2])
                if R is None
                else R
            )
            fields = dict(sensor_id=sid, scan=k, t=float(k), z=z, R=R, t_sent_ns=clock.now_ns())
            return msg.Measurement(**(fields | kw))

        def respond(cmd, tr):
            k = cmd.scan
            z = draw(good, cfg.seed, k - 1).scan.z[j]
            bad_el = np.array([[0.5, 2.0]])  # elevation beyond pi/2
            if k == 2:
                return meas(k, bad_el)
            for i, m in enumerate(
                (
                    meas(k, bad_el),
                    meas(k, np.zeros((1, 3)), R=np.eye(3)),  # not angle pairs
                    meas(k, z, target_ids=tuple(f"x{i}" for i in range(len(z)))),  # another kind's
                    meas(k, np.zeros((manager_node.MAX_LIST + 1, 2))),  # too long
                    meas(k, z, sensor_id="s1"),  # on s3's key
                )
            ):
                # numbered, as a sensor numbers what it sends (an unnumbered message is
                # refused before its content is looked at: missing_seq)
                bus.publish(key, msg.encode(m.evolve(seq=50_000 + 10 * k + i)))
            bus.publish(key, b"\x93garbage")
            return meas(k, z)

        return serve(
            sid, bus, "t", clock, stop, cfg.network, truth_ok=lambda tr: True, respond=respond,
            scans=cfg.scans, config=config_id(cfg),  # a node of this run's config
        )

    return run


@pytest.mark.timeout(60)
def test_malformed_lists_are_rejected_and_counted():
    cfg = _cfg(scans=3, seed=4, scan_timeout_s=1.0)
    result, _, tracks = run_network(cfg, {"s3": _bad_sensor(cfg, "s3")})
    assert result.completed and result.error is None
    r1, r2, r3 = result.scans.list()
    # scans 1 and 3: the good list came after the bad ones; the association is covnet run's
    for r in (r1, r3):
        assert r["associated"]
        _assert_same_scan(r, _reference(cfg, r["scan"]))
    # scan 2: only a malformed list from s3: not associated, counted, no tracks
    assert not r2["associated"] and r2["missing"] == ["s3"] and r2["lists_from"] == ["s1", "s2"]
    assert result.unassociated == 1 and not [t for t in tracks if t.scan == 2]
    assert result.stats.rejected == {
        "bad_measurement": 2 * 4 + 1,
        "key_mismatch": 2,
        "not_msgpack": 2,
    }
    doc = manager_node.association_doc(cfg, result)
    assert doc["summary"]["unassociated"] == 1 and doc["summary"]["associated"] == 2
    assert doc["scan"] == 3 and doc["triples"] == r3["triples"]


@pytest.mark.timeout(60)
def test_failed_sensor_scans_are_counted_not_associated():
    cfg = _cfg(scans=6, seed=3)
    result, _, tracks = run_network(cfg, kill_after_scan=2, victim="s2")
    assert result.completed and result.error is None
    events = result.failures
    assert events and events[0]["sensor"] == "s2" and events[0]["event"] == "failed"
    k_fail = events[0]["scan"]
    assert 3 <= k_fail <= 6
    for r in result.scans.list()[:2]:
        assert r["associated"]
        _assert_same_scan(r, _reference(cfg, r["scan"]))
    for r in result.scans.list()[k_fail - 1 :]:  # s2 seen failed: not commanded, nothing associated
        assert not r["associated"] and r["missing"] == ["s2"]
    assert result.unassociated >= 6 - k_fail + 1
    assert not [t for t in tracks if t.scan >= k_fail]


# --------------------------------------------------------------------------------------------
# real processes over zenoh
# --------------------------------------------------------------------------------------------


@pytest.mark.integration
@pytest.mark.timeout(90)
def test_up_equals_run_for_the_same_seed(covnet_proc, tmp_path):
    data = yaml.safe_load(PASSIVE.read_text())
    data["scans"] = 3
    cfg_path = tmp_path / "passive.yaml"
    cfg_path.write_text(yaml.safe_dump(data))
    out = tmp_path / "up"
    p = covnet_proc(["up", str(cfg_path), "--out", str(out), "--seed", "7"])
    assert p.wait(timeout=60) == 0, p.output()
    assert_nothing_left(out)
    for name in (
        "association.json",
        "config.json",
        "network.json",
        "processes.json",
        "recording.mcap",
        "run.json",
        "scene.png",
    ):
        assert (out / name).is_file(), name
    info = json.loads((out / "run.json").read_text())
    assert info["mode"] == "network" and info["kind"] == "passive" and info["completed"]
    assert info["scans_completed"] == 3 and info["scans_unassociated"] == 0
    assert info["failures"] == []
    doc = json.loads((out / "association.json").read_text())
    assert [r["scan"] for r in doc["scans"]] == [1, 2, 3]
    ref_out = tmp_path / "ref"
    r = covnet_proc(["run", str(cfg_path), "--out", str(ref_out), "--seed", "7"])
    assert r.wait(timeout=60) == 0, r.output()
    ref = json.loads((ref_out / "association.json").read_text())
    _assert_same_scan(doc["scans"][0], ref)
    assert doc["seed"] == ref["seed"] == 7 and doc["config_hash"] == ref["config_hash"]
    net = json.loads((out / "network.json").read_text())
    assert net["rejected"] == {}
    assert p.output().count("STATUS") == 0  # the launcher renders STATUS lines, never echoes them
    assert "scan(s), 3 associated" in p.output()
    docs = assert_visual_channels(out / "recording.mcap", [1, 2, 3], "world_km")
    assert [len(d["targets"]) for d in docs] == [len(r["triples"]) for r in doc["scans"]]
