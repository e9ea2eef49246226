"""``covnet up --sensors-per-process K`` (issue 17): several sensors per process, each with its own
session, liveliness token and heartbeat; ``processes.json`` names each sensor's host; killing a
host takes out its sensors and the allocation goes on without them."""

from __future__ import annotations

import json
import os
import re
import signal
from pathlib import Path

import pytest
import yaml
from multiproc import assert_nothing_left

from covnet.processes.up import default_sensors_per_process, hosted_by, sensor_hosts

pytestmark = [pytest.mark.integration, pytest.mark.timeout(180)]

LARGE = Path(__file__).resolve().parents[2] / "configs" / "large.yaml"
SPEED = 20.0  # scans per second in real time


def test_default_and_grouping():
    assert default_sensors_per_process(8, cores=2) == 1
    assert default_sensors_per_process(16, cores=2) == 1
    assert default_sensors_per_process(64, cores=2) == 16
    assert default_sensors_per_process(256, cores=2) == 64
    assert default_sensors_per_process(64, cores=48) == 1
    assert sensor_hosts(["a", "b", "c"], 1) == [("a", ["a"]), ("b", ["b"]), ("c", ["c"])]
    assert sensor_hosts(["a", "b", "c"], 2) == [("sensors@1", ["a", "b"]), ("sensors@2", ["c"])]


def test_a_host_left_with_one_sensor_still_hosts_it():
    """8 sensors by 7: ``sensors@2`` runs S8 alone; S8 was missing from ``processes.json``'s
    ``hosts`` and from the certificates checked before the start (its missing certificate then
    ended the run with an error line that did not always show)."""
    ids = [f"S{i}" for i in range(1, 9)]
    hosts = hosted_by(sensor_hosts(ids, 7))
    assert hosts == {**{s: "sensors@1" for s in ids[:7]}, "S8": "sensors@2"}
    assert hosted_by(sensor_hosts(ids, 1)) == {}  # a process per sensor: named after it


def _config(tmp_path: Path) -> Path:
    """The first 16 sensors of configs/large.yaml (sites 1 and 2 of every family), exact search."""
    d = yaml.safe_load(LARGE.read_text())
    d["sensors"] = d["sensors"][:16]
    d["scans"] = 80
    d["allocation"] = {"metrics": ["spectral"]}
    path = tmp_path / "hosts.yaml"
    path.write_text(yaml.safe_dump(d))
    return path


def test_killing_a_host_takes_out_its_sensors_and_the_run_goes_on(covnet_proc, tmp_path):
    cfg = _config(tmp_path)
    out = tmp_path / "run"
    p = covnet_proc(
        [
            "up",
            str(cfg),
            "--out",
            str(out),
            "--realtime",
            "--speed",
            str(SPEED),
            "--sensors-per-process",
            "4",
            "--no-figures",
            "--verbose",
        ]
    )
    assert p.wait_for("[manager] READY", timeout=60), p.output()
    pids = json.loads((out / "processes.json").read_text())
    ids = [s["id"] for s in yaml.safe_load(cfg.read_text())["sensors"]]
    hosts = pids["hosts"]
    assert set(hosts) == set(ids)
    assert {n for n in pids if n.startswith("sensors@")} == {f"sensors@{i}" for i in (1, 2, 3, 4)}
    assert all(hosts[sid] == f"sensors@{1 + i // 4}" for i, sid in enumerate(ids))
    # each hosted sensor is its own node: its own liveliness token and heartbeat
    victims = [sid for sid in ids if hosts[sid] == "sensors@1"]  # S1.1 .. S4.1, the best ones
    in_run = re.compile(r"^\[status\] spectral: (scan )?(1[5-9]|[2-7]\d)/80 ")
    assert p.wait_for(lambda s: in_run.search(s) is not None, timeout=30), p.output()
    os.kill(pids["sensors@1"], signal.SIGKILL)
    assert p.wait(timeout=90) == 0, p.output()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["completed"] is True
    events = summary["failures"]["spectral"]
    failed = {e["sensor"]: e["scan"] for e in events if e["event"] == "failed"}
    assert set(failed) == set(victims), events
    subsets = summary["metrics"]["spectral"]["subsets"]
    k_fail = max(failed.values())
    assert any(set(victims) & set(s) for s in subsets[: min(failed.values()) - 1])  # in use
    assert all(not set(victims) & set(s) for s in subsets[k_fail - 1 :])  # never again
    assert all(s for s in subsets[k_fail - 1 :])  # the others carried on
    net = json.loads((out / "network.json").read_text())
    assert net["lost"] <= len(victims)  # at most one measurement each, of the scan they died in
    for sid in ids:
        if sid not in victims:
            assert re.search(rf"\[sensors@\d\] {re.escape(sid)}: stopped: ", p.output()), p.output()
    assert_nothing_left(out)
