"""Malformed traffic on every key the network subscribes to, during a real ``covnet up`` run:
every bad message is counted by reason and dropped, and the run's subsets and estimates are
exactly those of a clean ``covnet run``."""

from __future__ import annotations

import json
import re
import threading

import msgpack
import numpy as np
import pytest
import yaml

from covnet.cli.app import main as covnet_main
from covnet.runs.rundir import load_arrays
from covnet.wire import messages as msg

pytestmark = [pytest.mark.integration, pytest.mark.timeout(180)]

SENSORS = tuple(f"S{i}" for i in range(1, 9))  # the paper's


def _arr(a) -> msgpack.ExtType:
    a = np.asarray(a, dtype="<f8")
    return msgpack.ExtType(1, msgpack.packb(["<f8", list(a.shape), a.tobytes()]))


def _raw(d: dict) -> bytes:
    return msgpack.packb(d, use_bin_type=True)


def bad_payloads(run: str) -> list[tuple[str, bytes, str]]:
    """(key, payload, expected reason) for every subscribed key."""
    good_meas = msg.encode(
        msg.Measurement(sensor_id="S1", scan=1, t=1.0, z=np.zeros((1, 2)), R=np.eye(2), t_sent_ns=1)
    )
    good_cmd = msg.encode(msg.Command(scan=1, t=1.0, enabled=("S1",), t_sent_ns=1))
    good_truth = msg.encode(msg.Truth(scan=1, t=1.0, target_ids=("T1",), states=np.zeros((1, 4))))
    meas = {
        "v": 1,
        "k": "meas",
        "sensor_id": "S1",
        "scan": 1,
        "t": 1.0,
        "z": _arr([[0.0, 0.0]]),
        "R": _arr(np.eye(2)),
        "t_sent_ns": 1,
        "episode": 0,
    }
    out: list[tuple[str, bytes, str]] = []
    keys = {
        "meas": msg.measurement_key(run, "S1"),
        "cmd": msg.command_key(run, SENSORS),  # every sensor hears it
        "truth": msg.truth_key(run),
        "hb": msg.heartbeat_key(run, "sensor", "S1"),
    }
    for name, key in keys.items():
        out.append((key, b"\xc1garbage\x00\xff", "not_msgpack"))
        good = {"meas": good_meas, "cmd": good_cmd, "truth": good_truth, "hb": good_meas}[name]
        out.append((key, good[: len(good) // 2], "truncated"))
        wrong_version = msgpack.unpackb(good, ext_hook=lambda c, d: msgpack.ExtType(c, d))
        wrong_version["v"] = 99
        out.append((key, msgpack.packb(wrong_version), "bad_version"))
    out.append((keys["meas"], _raw(meas | {"z": _arr([[0.0, 0.0, 0.0]])}), "bad_shape"))
    out.append((keys["meas"], _raw(meas | {"z": _arr([[np.nan, 0.0]])}), "non_finite"))
    out.append((keys["meas"], _raw(meas | {"scan": True}), "bad_type"))
    out.append(
        (
            keys["truth"],
            _raw(
                {
                    "v": 1,
                    "k": "truth",
                    "scan": 1,
                    "t": 1.0,
                    "target_ids": ["T1"],
                    "states": _arr([[np.inf, 0, 0, 0]]),
                }
            ),
            "non_finite",
        )
    )
    out.append(
        (
            keys["cmd"],
            _raw(
                {
                    "v": 1,
                    "k": "cmd",
                    "scan": 1,
                    "t": 1.0,
                    "enabled": "S1",
                    "t_sent_ns": 1,
                    "episode": 0,
                }
            ),
            "bad_type",
        )
    )
    out.append((keys["hb"], _raw({"v": 1, "k": "hb", "role": "sensor"}), "missing_field"))
    out.append((keys["cmd"], good_cmd, "key_mismatch"))  # the key names all 8, it enables S1
    return out


def test_garbage_on_every_key_is_counted_and_dropped(covnet_proc, tmp_path, paper_path):
    from covnet.wire.zenoh_bus import ZenohBus, zenoh_config

    data = yaml.safe_load(paper_path.read_text())
    data["scans"] = 1500  # long enough in lockstep to inject while it runs (~5 s)
    data["network"] = {"record": False}
    cfg = tmp_path / "long.yaml"
    cfg.write_text(yaml.safe_dump(data))
    ref = tmp_path / "ref"
    assert covnet_main(["run", str(cfg), "--out", str(ref), "--metric", "svd", "--no-figures"]) == 0

    out = tmp_path / "run"
    p = covnet_proc(["up", str(cfg), "--out", str(out), "--metric", "svd", "--no-figures"])
    line = p.wait_for("[launcher] run ", timeout=30)
    assert line, p.output()
    run_id, router = re.search(r"run (\S+): router (\S+),", line).groups()
    assert p.wait_for("[manager] READY", timeout=60), p.output()
    payloads = bad_payloads(run_id)
    done = threading.Event()
    rounds = 0
    with ZenohBus.open(zenoh_config("client", connect=[router])) as bus:
        while not done.is_set() and rounds < 3:
            for key, payload, _reason in payloads:
                bus.publish(key, payload)
            rounds += 1
            done.wait(0.3)  # spread the rounds over the run (heartbeats report counts)
    assert p.wait(timeout=120) == 0, p.output()

    got = json.loads((out / "summary.json").read_text())["metrics"]["svd"]
    want = json.loads((ref / "summary.json").read_text())["metrics"]["svd"]
    assert got["subsets"] == want["subsets"]
    a, b = load_arrays(out / "arrays.npz"), load_arrays(ref / "arrays.npz")
    np.testing.assert_array_equal(a["x_est.svd"], b["x_est.svd"])
    np.testing.assert_array_equal(a["P_post.svd"], b["P_post.svd"])

    net = json.loads((out / "network.json").read_text())
    meas_key = msg.measurement_key(run_id, "S1")
    hb_key = msg.heartbeat_key(run_id, "sensor", "S1")
    expect_mgr: dict[str, dict[str, int]] = {}
    expect_node: dict[str, int] = {}
    for key, _payload, reason in payloads:
        if key in (meas_key, hb_key):
            expect_mgr.setdefault(key, {}).setdefault(reason, 0)
            expect_mgr[key][reason] += rounds
        elif key == msg.command_key(run_id, SENSORS):
            expect_node[reason] = expect_node.get(reason, 0) + rounds
    assert net["rejected_by_key"] == expect_mgr
    # every sensor hears the command and truth keys; the world of a run this short sends all
    # the truth up front and hears no command (TRUTH_UPFRONT_MAX_SCANS), so it rejects nothing
    truth_reasons = {r: rounds for k, _p, r in payloads if k == msg.truth_key(run_id)}
    for node, counts in net["rejected_by_node"].items():
        merged = dict(expect_node)
        for r, n in truth_reasons.items():
            merged[r] = merged.get(r, 0) + n
        assert counts == merged, (node, counts)
    assert set(net["rejected_by_node"]) == {f"S{i}" for i in range(1, 9)}
