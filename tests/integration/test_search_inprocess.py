"""The manager's loop with ``allocation.search: bounded`` (issue 17), world, sensors and manager
as threads over one InMemoryHub: the same decisions as ``covnet run`` and the certified
``value``, ``lower_bound``, ``gap`` of every scan in the live status and the episode's log."""

from __future__ import annotations

import math
import threading
from pathlib import Path

import numpy as np
import yaml
from nodethreads import NodeThreads

from covnet.clock import WallClock
from covnet.covariance_control.config import from_dict
from covnet.covariance_control.simulate import run_metric
from manager import covariance as manager_node
from sensors import covariance as sensor_node
from world import covariance as world_node

LARGE = Path(__file__).resolve().parents[2] / "configs" / "large.yaml"


def test_bounded_search_in_the_manager_reports_its_gap():
    d = yaml.safe_load(LARGE.read_text())
    d["sensors"] = d["sensors"][:34]
    d["scans"] = 12
    d["allocation"] = {"metrics": ["kl"], "search": "bounded", "gap": 0.02, "node_limit": 4000}
    d["network"] = {"record": False}
    sc = from_dict(d)
    nodes = NodeThreads()
    nodes.start("world", lambda bus, ev: world_node.run(sc, bus, "t", WallClock(), ev))
    for sid in sc.sensor_ids:
        nodes.start(
            sid, lambda bus, ev, sid=sid: sensor_node.run(sc, sid, bus, "t", WallClock(), ev)
        )
    statuses = []
    mbus = nodes.bus("manager")
    try:
        result = manager_node.run(
            sc, mbus, "t", WallClock(), threading.Event(), on_status=statuses.append
        )
    finally:
        nodes.close()
        mbus.close()
    assert result.completed and result.error is None
    ref = run_metric(sc, "kl")
    got = result.episodes["kl"].as_run(34)
    np.testing.assert_array_equal(got.enabled, ref.enabled)
    np.testing.assert_array_equal(got.value, ref.value)
    np.testing.assert_array_equal(got.lower_bound, ref.lower_bound)
    np.testing.assert_array_equal(got.gap, ref.gap)
    assert [st["scan"] for st in statuses] == list(range(1, 13))
    for st, v, lb, g in zip(statuses, ref.value, ref.lower_bound, ref.gap, strict=True):
        assert st["value"] == v and st["lower_bound"] == lb and st["gap"] == g
        assert f"gap {100 * g:.3g} %" in st["info"] and math.isfinite(st["gap"])
