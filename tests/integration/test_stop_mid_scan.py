"""A manager stopped in the middle of a scan (Ctrl-C or SIGTERM while it waits for the scan's
time in real time, or for the scan's measurements) keeps only the scans it did.  It fused what
had come by then and recorded the cut scan as done: a last scan with nothing fused (``P_post``
equal to ``P_pred``) but its sensors enabled, counted in ``scans_completed``, the summary's
RMSE and NEES and ``arrays.npz``.  World, sensors and manager run as threads over one
InMemoryHub; the scans kept equal ``covnet run``'s."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from nodethreads import NodeThreads

from covnet.clock import WallClock
from covnet.covariance_control.config import from_dict, normalised
from covnet.covariance_control.simulate import run_metric
from manager import covariance as manager_node
from sensors import covariance as sensor_node
from world import covariance as world_node

pytestmark = pytest.mark.timeout(120)
STOP_AFTER = 3


@pytest.mark.parametrize("realtime", [False, True])
def test_a_scan_cut_by_a_stop_is_not_kept(paper, realtime):
    data = normalised(paper)
    data["scans"] = 12
    data["network"]["record"] = False
    data["allocation"]["metrics"] = ["spectral"]
    sc = from_dict(data)
    clock = WallClock(speed=4.0) if realtime else WallClock()
    nodes = NodeThreads()
    nodes.start("world", lambda bus, ev: world_node.run(sc, bus, "t", clock, ev))
    for sid in sc.sensor_ids:
        nodes.start(sid, lambda bus, ev, sid=sid: sensor_node.run(sc, sid, bus, "t", clock, ev))
    stop = threading.Event()

    def on_status(st):
        # lockstep: scan k's status goes out once scan k+1's command has, before its
        # measurements are collected; real time: as scan k ends, so the stop comes 50 ms
        # later, while scan k+1's time is awaited (at --speed 4 a scan is 250 ms) or, on a
        # slow machine, while its measurements are
        if st["scan"] == STOP_AFTER:
            if realtime:
                threading.Timer(0.05, stop.set).start()
            else:
                stop.set()

    mbus = nodes.bus("manager")
    try:
        result = manager_node.run(
            sc, mbus, "t", clock, stop, realtime=realtime, on_status=on_status
        )
    finally:
        nodes.close()
        mbus.close()
    assert not result.completed
    run = result.episodes["spectral"].as_run(len(sc.sensor_ids))
    n = run.enabled.shape[0]
    assert n == STOP_AFTER, n
    assert all(not np.array_equal(run.P_post[i], run.P_pred[i]) for i in range(n))
    ref = run_metric(sc, "spectral")
    if not realtime:  # real time: a scan's measurements may miss its deadline under load
        np.testing.assert_array_equal(run.enabled, ref.enabled[:n])
        np.testing.assert_array_equal(run.P_post, ref.P_post[:n])
