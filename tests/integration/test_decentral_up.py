"""Decentralized modes over real zenoh sessions between real processes (127.0.0.1, free port,
per-run key prefix): a centre fusing local tracks, and peer nodes with no centre."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal

import numpy as np
import pytest
import yaml
from multiproc import CovnetProcess, assert_nothing_left
from traffic_check import assert_compare_counts_what_was_sent

from covnet.cli.app import main as covnet_main
from covnet.covariance_control.replay import RECORDING, replay_run
from covnet.runs.recording import RecordingReader, RecordingWriter, read_metadata
from covnet.runs.rundir import load_arrays
from covnet.wire import messages as msg

pytestmark = [pytest.mark.integration, pytest.mark.timeout(240)]


def _config(tmp_path, paper_path, name, scans, fusion):
    data = yaml.safe_load(paper_path.read_text())
    data["scans"] = scans
    data["fusion"] = fusion
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def _run_both(tmp_path, cfg, metric):
    ref, out = tmp_path / "ref", tmp_path / "up"
    args = ["--metric", metric, "--no-figures"]
    assert covnet_main(["run", str(cfg), "--out", str(ref), *args]) == 0
    p = CovnetProcess(["up", str(cfg), "--out", str(out), *args])
    try:
        rc = p.wait(timeout=200)
    finally:
        p.stop()
    assert rc == 0, p.output()
    assert_nothing_left(out)
    return ref, out


@pytest.mark.parametrize("mode", ["info", "ci"])
def test_centre_fusing_local_tracks_equals_the_in_process_run(tmp_path, paper_path, mode):
    cfg = _config(tmp_path, paper_path, mode, 60, {"mode": mode})
    ref, out = _run_both(tmp_path, cfg, "spectral")
    a, b = (
        json.loads((ref / "summary.json").read_text()),
        json.loads((out / "summary.json").read_text()),
    )
    assert b["completed"] is True and b["fusion"] == a["fusion"]
    assert b["metrics"]["spectral"]["subsets"] == a["metrics"]["spectral"]["subsets"]
    x, y = load_arrays(ref / "arrays.npz"), load_arrays(out / "arrays.npz")
    np.testing.assert_allclose(y["x_est.spectral"], x["x_est.spectral"], rtol=0, atol=1e-12)
    np.testing.assert_allclose(y["P_post.spectral"], x["P_post.spectral"], rtol=0, atol=1e-12)
    # obedience: one local track per enabled scan, from each sensor, and nothing rejected
    net = json.loads((out / "network.json").read_text())
    for sid, used in b["metrics"]["spectral"]["usage"].items():
        keys = [k for k in net["received"] if k.endswith(f"/sensor/{sid}/meas")]
        assert sum(net["received"][k]["messages"] for k in keys) == used, sid
    assert net["rejected"] == {} and net["lost"] == 0
    assert_compare_counts_what_was_sent(out, mode)  # compare's bytes are the recording's
    # the recording of local tracks re-fuses to the same summary, byte for byte
    assert covnet_main(["replay", str(out)]) == 0
    assert (out / "replay" / "summary.json").read_bytes() == (out / "summary.json").read_bytes()


def test_peer_ring_equals_the_in_process_run_and_nodes_agree(tmp_path, paper_path):
    cfg = _config(tmp_path, paper_path, "ring", 40, {"mode": "peer", "peer": {"graph": "ring"}})
    ref, out = _run_both(tmp_path, cfg, "abs_trace")
    b = json.loads((out / "summary.json").read_text())
    assert b["completed"] is True and b["fusion"] == "peer-info-ring"
    assert b["peer"]["abs_trace"]["agreement"] is True
    x, y = load_arrays(ref / "arrays.npz"), load_arrays(out / "arrays.npz")
    for sid in b["sensor_ids"]:
        for name in ("x_est", "P_post"):
            key = f"{name}.abs_trace.{sid}"
            np.testing.assert_allclose(y[key], x[key], rtol=0, atol=1e-12, err_msg=key)
    # every array of the run, the first node's prediction included (the network wrote NaN)
    assert set(x) == set(y)
    for key in x:
        np.testing.assert_array_equal(y[key], x[key], err_msg=key)
    names = set(json.loads((out / "processes.json").read_text()))
    assert "manager" in names  # the router and monitor: it neither decides nor fuses
    assert_compare_counts_what_was_sent(out, "peer-info")  # compare's bytes: the recording's
    # the recording re-fuses node by node (the engine of each node alone) to the same summary
    assert covnet_main(["replay", str(out)]) == 0
    assert (out / "replay" / "summary.json").read_bytes() == (out / "summary.json").read_bytes()
    report = json.loads((out / "replay" / "replay.json").read_text())
    assert report["identical"] is True and report["differences"] == [], report
    assert report["counts"]["node_status"] >= 40 * len(b["sensor_ids"]), report["counts"]
    # a local track's bits changed in the recording: the nodes that fused it differ
    tampered = tmp_path / "tampered"
    shutil.copytree(out, tampered, ignore=shutil.ignore_patterns("replay"))
    run_id = json.loads((out / "run.json").read_text())["run_id"]
    samples = list(RecordingReader(out / RECORDING).samples())
    idx, raw = next(
        (i, m.x.tobytes())
        for i, s in enumerate(samples)
        if s.key.endswith("/meas") and (m := msg.decode_as(s.payload, msg.LocalTrack)).scan == 10
    )
    with RecordingWriter(
        tampered / RECORDING, run_id=run_id, metadata=read_metadata(out / RECORDING)
    ) as w:
        for i, s in enumerate(samples):
            payload = s.payload
            if i == idx:
                at = payload.index(raw) + 5  # x[0]'s mantissa: a valid, finite change
                payload = payload[:at] + bytes([payload[at] ^ 1]) + payload[at + 1 :]
            w.write(s.key, payload, s.t_recv_ns, s.t_sent_ns)
    rep = replay_run(tampered)
    assert not rep.identical
    assert any(
        "scan 10: the replayed estimate differs from the node's Track" in d for d in rep.differences
    ), rep.differences


def test_a_killed_peer_is_dropped_from_every_decision(covnet_proc, tmp_path, paper_path):
    victim = "S3"  # used often by abs_trace
    # 150 scans (~30 a second here): killed at scan 5 or soon after, failed within a second
    cfg = _config(tmp_path, paper_path, "kill", 150, {"mode": "peer", "peer": {"graph": "ring"}})
    out = tmp_path / "run"
    p = covnet_proc(["up", str(cfg), "--out", str(out), "--metric", "abs_trace", "--no-figures"])
    assert p.wait_for("[manager] READY", timeout=90), p.output()
    m = p.wait_for(
        lambda s: re.search(r"scan (\d+)/", s) and int(re.search(r"scan (\d+)/", s)[1]) >= 5,
        timeout=90,
    )
    assert m, p.output()
    pids = json.loads((out / "processes.json").read_text())
    os.kill(pids[victim], signal.SIGKILL)
    assert p.wait(timeout=200) == 0, p.output()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["completed"] is True
    peer = summary["peer"]["abs_trace"]
    assert peer["agreement"] is True  # every node decided the same at every scan it ran
    failed = [e for e in summary["failures"]["abs_trace"] if e["sensor"] == victim]
    assert failed, summary["failures"]
    k_fail = failed[0]["scan"]
    assert k_fail < 150
    arrays = load_arrays(out / "arrays.npz")
    ids = summary["sensor_ids"]
    for sid in ids:
        if sid == victim:
            continue
        x = arrays.get(f"x_est.abs_trace.{sid}")
        assert x is not None and len(x) == 150, sid  # the survivors finished
    # from the failure on, no survivor enables the victim
    subsets = summary["metrics"]["abs_trace"]["subsets"]
    assert all(victim not in s for s in subsets[k_fail - 1 :])
    assert_nothing_left(out)
    # the recording replays the failure too: each node's decisions without the victim
    assert covnet_main(["replay", str(out)]) == 0
    assert (out / "replay" / "summary.json").read_bytes() == (out / "summary.json").read_bytes()


def test_an_interrupted_peer_run_replays_identically(covnet_proc, tmp_path, paper_path):
    """Ctrl-C to ``covnet up --fusion peer`` mid-run: exit 130, ``run.json`` says how many
    scans were done (the launcher printed "scans unknown"), no node is called failed for
    leaving, and ``covnet replay`` reproduces summary.json (it said DIFFERS: the observer had
    stopped taking the nodes' reports at once, one scan short of the recording, and nodes cut
    mid-scan had named their peers failed)."""
    cfg = _config(tmp_path, paper_path, "int", 300, {"mode": "peer", "peer": {"graph": "full"}})
    out = tmp_path / "run"
    p = covnet_proc(["up", str(cfg), "--out", str(out), "--metric", "spectral", "--no-figures"])
    assert p.wait_for("[manager] READY", timeout=90), p.output()
    # the launcher prints a status line a second: the second one is some scans into the run
    scans = re.compile(r"\[status\] spectral: scan (\d+)/")
    m = p.wait_for(lambda s: (g := scans.search(s)) is not None and int(g[1]) > 1, timeout=90)
    assert m, p.output()
    os.killpg(p.proc.pid, signal.SIGINT)  # as a terminal's Ctrl-C
    assert p.wait(timeout=60) == 130, p.output()
    assert "Traceback" not in p.output(), p.output()
    assert_nothing_left(out)
    info = json.loads((out / "run.json").read_text())
    summary = json.loads((out / "summary.json").read_text())
    assert info["status"] == "interrupted", info
    done = info["scans_completed"]["spectral"]
    assert done == summary["scans_completed"]["spectral"] and 1 < done < 300, (info, summary)
    assert f"(interrupted: spectral {done})" in p.output(), p.output()
    assert summary["failures"] == {"spectral": []}, summary["failures"]
    assert covnet_main(["replay", str(out)]) == 0
    assert (out / "replay" / "summary.json").read_bytes() == (out / "summary.json").read_bytes()
