"""``covnet up configs/mobile.yaml``: the mobile network (world, one process per sensor, the
manager) reproduces ``covnet run`` for the same seed, in threads over an in-memory bus and as
real processes over zenoh; a sensor that dies leaves the problem and the run goes on."""

from __future__ import annotations

import json
import os
import re
import signal
import threading

import numpy as np
import pytest
import yaml
from multiproc import REPO, assert_nothing_left
from nodethreads import NodeThreads
from visual_check import assert_visual_channels

from covnet.clock import WallClock
from covnet.mobile.config import load, with_overrides
from covnet.mobile.simulate import TIMING_FIELDS, run
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


def run_network(cfg, *, solver=None, kill_after_scan=None, victim=None):
    if solver is not None:  # --solver is a change of the config, for every process alike
        cfg = with_overrides(cfg, str(MOBILE), solver=solver)
    nodes = NodeThreads()
    nodes.start("world", lambda bus, ev: world_node.run(cfg, bus, "t", WallClock(), ev))
    for sid in cfg.sensor_ids:
        nodes.start(
            sid, lambda bus, ev, sid=sid: sensor_node.run(cfg, sid, bus, "t", WallClock(), ev)
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
