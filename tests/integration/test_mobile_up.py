"""``covnet up configs/mobile.yaml``: the mobile network (world, one process per sensor, the
manager) reproduces ``covnet run`` for the same seed, in threads over an in-memory bus and as
real processes over zenoh; a sensor that dies leaves the problem and the run goes on."""

from __future__ import annotations

import dataclasses
import json
import os
import re
import signal
import threading
import time

import numpy as np
import pytest
import yaml
from multiproc import REPO, assert_nothing_left
from nodethreads import Forger, NodeThreads
from visual_check import assert_visual_channels

from covnet.clock import WallClock
from covnet.mobile.config import load, with_overrides
from covnet.mobile.simulate import TIMING_FIELDS, run
from covnet.wire import messages as msg
from manager import mobile as manager_node
from sensors import mobile as sensor_node
from world import mobile as world_node

MOBILE = REPO / "configs" / "mobile.yaml"
# every deterministic array of a run (wall times excluded)
COMPARED = (
    "truth x_est P_post platforms modes assign detected pd_true usage objective status "
    "fractional J_lp J_post J_star J_relax gap conflicts mip_gap exact_status"
).split()


def _assert_same_run(got: dict, ref: dict) -> None:
    for name in COMPARED:
        np.testing.assert_array_equal(got[name], ref[name], err_msg=name)


def _cfg(scans: int, seed: int = 0, record: bool = False):
    cfg = load(MOBILE)
    net = cfg.network.model_dump() | {"record": record}
    return with_overrides(cfg, str(MOBILE), scans=scans, seed=seed, network=net)


# --------------------------------------------------------------------------------------------
# threads over one InMemoryHub
# --------------------------------------------------------------------------------------------


def run_network(cfg, *, solver=None, kill_after_scan=None, victim=None, wrap_bus=None):
    """``wrap_bus``: sensor id -> a wrapper of that sensor's bus (a node that misbehaves)."""
    if solver is not None:  # --solver is a change of the config, for every process alike
        cfg = with_overrides(cfg, str(MOBILE), solver=solver)
    nodes = NodeThreads()
    nodes.start("world", lambda bus, ev: world_node.run(cfg, bus, "t", WallClock(), ev))
    for sid in cfg.sensor_ids:
        wrap = (wrap_bus or {}).get(sid, lambda bus: bus)
        nodes.start(
            sid,
            lambda bus, ev, sid=sid, wrap=wrap: sensor_node.run(
                cfg, sid, wrap(bus), "t", WallClock(), ev
            ),
        )

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
    return result, nodes.stats


@pytest.mark.timeout(60)
@pytest.mark.parametrize("solver", ["lp", "milp"])
def test_in_process_network_equals_run(solver):
    cfg = _cfg(scans=15, seed=2)
    result, stats = run_network(cfg, solver=solver)
    assert result.completed and result.error is None
    got = result.as_run()
    ref = run(cfg, solver)
    _assert_same_run(got.arrays(), ref.arrays())
    # obedience: each sensor answered every scan (it was alive), measuring only its targets
    for sid in cfg.sensor_ids:
        assert stats[sid].measurements_sent == stats[sid].enabled_scans == cfg.scans
        assert not stats[sid].rejected
    assert result.stats.rejected == {} and result.stats.lost == 0


@pytest.mark.timeout(60)
def test_in_process_failed_sensor_leaves_the_problem():
    cfg = _cfg(scans=20)
    j = cfg.sensor_ids.index("S1")  # S1 observes T1 from scan 1 on
    ref = run(cfg)
    assert (ref.assign == j).any()
    result, _ = run_network(cfg, kill_after_scan=3, victim="S1")
    assert result.completed
    got = result.as_run()
    assert got.assign.shape == (20, 3)
    events = result.failures
    assert events and events[0]["sensor"] == "S1" and events[0]["event"] == "failed"
    k_fail = events[0]["scan"]
    assert k_fail <= 6
    assert not (got.assign[k_fail - 1 :] == j).any()  # never assigned once seen failed
    # its platform stays where it was; the scans before the failure are covnet run's
    assert np.all(got.platforms[k_fail:, j] == got.platforms[k_fail - 1, j])
    np.testing.assert_array_equal(got.x_est[:4], ref.x_est[:4])


@pytest.mark.timeout(60)
def test_a_dead_world_does_not_stall_every_later_scan():
    """The mobile world publishes each truth on the scan's command: once it died (and is not
    restarted), every later scan waited network.scan_timeout_s (10 s) for sensors that wait for
    a truth that never comes (a 100-scan run whose world died at scan 20: 13 more minutes).
    Now a scan waits for them at most loop.WORLD_GONE_WAIT_S while the world is down."""
    from manager.loop import WORLD_GONE_WAIT_S

    cfg = _cfg(scans=12)
    assert cfg.network.scan_timeout_s == 10.0
    t0 = time.monotonic()
    result, _ = run_network(cfg, kill_after_scan=3, victim="world")
    assert result.completed and result.error is None
    # the scans after the world stopped fused nothing, and none waited the scan timeout
    assert result.stats.missing_at_deadline >= 8
    assert time.monotonic() - t0 < 9 * 10.0 / 2
    assert WORLD_GONE_WAIT_S < cfg.network.scan_timeout_s


FORGERIES = {
    # detections moved 20 km east: fused, they took T1's track 16 km away for good
    "outside_gate": lambda m: dataclasses.replace(m, z=m.z + np.array([20_000.0, 0.0])),
    # a platform state far away (finite): the manager's update raised, the manager died
    "bad_platform": lambda m: dataclasses.replace(m, platform=np.array([1e200, 0.0, 0.0, 0.0])),
    # a platform 500 m off: it was taken as the position of the next decision
    "bad_platform_near": lambda m: dataclasses.replace(m, platform=m.platform + [500.0, 0, 0, 0]),
}


@pytest.mark.timeout(60)
@pytest.mark.parametrize("forgery", sorted(FORGERIES))
def test_a_forged_mobile_measurement_is_counted_and_never_fused(forgery):
    """The mobile manager fused whatever a sensor sent that had the right shapes: detections
    moved 20 km, a platform state of 1e200 m (which killed it).  Now the platform must be where
    its commanded mode took it and each detection must pass the validation gate; the rest is
    counted under the sensor's key and dropped, and the run goes on."""
    cfg = _cfg(scans=12)
    # the manager waits for S1's genuine answer until the scan's timeout: keep it short
    net = cfg.network.model_dump() | {"scan_timeout_s": 0.3}
    cfg = with_overrides(cfg, str(MOBILE), network=net)
    change = FORGERIES[forgery]
    result, stats = run_network(cfg, wrap_bus={"S1": lambda bus: Forger(bus, change)})
    assert result.completed and result.error is None
    rejected = result.stats.rejected_by_key.get(msg.measurement_key("t", "S1"), {})
    reason = forgery.removesuffix("_near")
    assert set(rejected) == {reason}
    sent = stats["S1"]
    if reason == "bad_platform":  # every one of S1's answers
        assert rejected[reason] == sent.measurements_sent == cfg.scans
    else:  # those with a detection (an empty answer has nothing to gate or drop)
        assert 0 < rejected[reason] <= sent.measurements_sent
    got = result.as_run()
    err = np.hypot(got.x_est[..., 0] - got.truth[..., 0], got.x_est[..., 2] - got.truth[..., 2])
    assert err.max() < 1000.0  # metres: every track on its target
    # the platforms are where the commanded modes took them (the world's own moves)
    ref = run(with_overrides(cfg, str(MOBILE), scans=1))
    np.testing.assert_array_equal(got.platforms[0], ref.platforms[0])


# --------------------------------------------------------------------------------------------
# real processes over zenoh
# --------------------------------------------------------------------------------------------


def _write_config(tmp_path, **changes):
    data = yaml.safe_load(MOBILE.read_text())
    data.update(changes)
    path = tmp_path / "mobile.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.integration
@pytest.mark.timeout(90)
def test_up_equals_run_for_the_same_seed(covnet_proc, tmp_path):
    cfg_path = _write_config(tmp_path, scans=15)
    out = tmp_path / "up"
    p = covnet_proc(["up", str(cfg_path), "--out", str(out), "--seed", "3", "--no-figures"])
    assert p.wait(timeout=60) == 0, p.output()
    assert_nothing_left(out)
    for name in ("summary.json", "arrays.npz", "config.json", "network.json", "recording.mcap"):
        assert (out / name).is_file(), name
    info = json.loads((out / "run.json").read_text())
    assert info["mode"] == "network" and info["completed"] and info["failures"] == []
    ref_out = tmp_path / "ref"
    r = covnet_proc(["run", str(cfg_path), "--out", str(ref_out), "--seed", "3", "--no-figures"])
    assert r.wait(timeout=60) == 0, r.output()
    with np.load(out / "arrays.npz") as a, np.load(ref_out / "arrays.npz") as b:
        assert set(a.files) == set(b.files)
        _assert_same_run(
            {k: a[k] for k in a.files if k not in TIMING_FIELDS},
            {k: b[k] for k in b.files if k not in TIMING_FIELDS},
        )
    s_up = json.loads((out / "summary.json").read_text())
    s_ref = json.loads((ref_out / "summary.json").read_text())
    assert "decision_time_s" not in s_up  # wall-clock facts: in run.json
    assert s_up == s_ref
    net = json.loads((out / "network.json").read_text())
    assert net["rejected"] == {}
    docs = assert_visual_channels(out / "recording.mcap", list(range(1, 16)), "world_m")
    assert all(len(d["targets"]) == 3 and d["n_active"] >= 1 for d in docs)


@pytest.mark.integration
@pytest.mark.timeout(90)
def test_up_sensor_killed_leaves_the_problem(covnet_proc, tmp_path):
    # real time at 20 scans/s: about 3 s of scans, long enough to kill S1 mid-run
    cfg_path = _write_config(tmp_path, scans=60, compare_exact=False)
    out = tmp_path / "run"
    p = covnet_proc(
        ["up", str(cfg_path), "--out", str(out), "--realtime", "--speed", "20", "--no-figures"]
    )
    assert p.wait_for("[manager] READY", timeout=60), p.output()
    assert p.wait_for(lambda s: re.search(r"scan ([5-9]|\d\d)/", s) is not None, timeout=30)
    pids = json.loads((out / "processes.json").read_text())
    os.kill(pids["S1"], signal.SIGKILL)
    assert p.wait(timeout=60) == 0, p.output()
    assert_nothing_left(out)
    info = json.loads((out / "run.json").read_text())
    assert info["completed"] and info["scans_completed"] == 60
    failed = [ev for ev in info["failures"] if ev["sensor"] == "S1"]
    assert failed and failed[0]["event"] == "failed"
    k_fail = failed[0]["scan"]
    with np.load(out / "arrays.npz") as a:
        assign = a["assign"]
    assert not (assign[k_fail - 1 :] == 0).any()  # S1 is never assigned once seen failed
    assert (assign[k_fail - 1 :] >= 0).any()  # the others go on observing
    summary = json.loads((out / "summary.json").read_text())
    assert summary["scans"] == 60 and set(summary["targets"]) == {"T1", "T2", "T3"}
