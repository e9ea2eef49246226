"""Surveillance over the bus: the world publishes the targets present at each scan, each
command names every enabled sensor's mode (a track ``K<id>`` or a search cell ``C<c>``) and its
window, each sensor returns every target inside it and its clutter, the manager steps the same
engine.  In lockstep it is ``covnet run`` bit for bit (in memory and over zenoh between real
processes), and ``covnet replay`` reproduces it from the recording."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from test_multitarget_up import run_network

from covnet.covariance_control import drive
from covnet.covariance_control.config import from_dict

ROOT = Path(__file__).resolve().parents[2]
FIELDS = ("gospa", "ospa", "n_confirmed", "n_tentative", "u", "search_dwells", "track_dwells",
          "value")  # fmt: skip


def short_data(scans: int = 14) -> dict:
    data = yaml.safe_load((ROOT / "configs" / "surveillance.yaml").read_text())
    data["scans"] = scans
    for t in data["targets"]:  # everyone in by mid-run; A3's turn inside it
        t["appears_at_scan"] = min(t.get("appears_at_scan", 1), scans // 2)
        t.pop("leaves_at_scan", None)
        for m in t.get("manoeuvres", []):
            m.update(from_scan=scans // 2, to_scan=scans - 1)
    data["targets"][-1]["leaves_at_scan"] = scans - 2
    return data


def test_in_memory_network_equals_run():
    data = short_data()
    data["network"] = {"record": False}
    sc = from_dict(data)
    result, stats = run_network(sc, ["spectral"])  # the many-target test's harness
    assert result.completed and result.error is None
    assert result.stats.rejected == {} and result.stats.lost == 0
    ref = drive.run(sc, "spectral").run
    got = result.episodes["spectral"].as_run()
    assert ref.search_dwells.sum() > 0 and ref.n_tracks_started > 0
    for f in FIELDS:
        np.testing.assert_array_equal(getattr(got, f), getattr(ref, f), err_msg=f)
    assert got.tracks[-1][0][0] == ref.tracks[-1][0][0]
    for a, b in zip(got.tracks, ref.tracks, strict=True):
        assert [(i, s) for i, s, _, _ in a] == [(i, s) for i, s, _, _ in b]
        for (_, _, xa, Pa), (_, _, xb, Pb) in zip(a, b, strict=True):
            assert np.array_equal(xa, xb) and np.array_equal(Pa, Pb)
    sent = sum(stats[sid].measurements_sent for sid in sc.sensor_ids)
    assert sent == int(ref.search_dwells.sum() + ref.track_dwells.sum())


@pytest.mark.integration
@pytest.mark.timeout(240)
def test_up_equals_run_and_replays(tmp_path):
    """12 sensor processes over zenoh in lockstep: covnet run's results; covnet replay
    reproduces the summary from the recording."""
    from multiproc import CovnetProcess, assert_nothing_left

    from covnet.cli.app import main as covnet_main
    from covnet.runs.rundir import load_arrays

    data = short_data(10)
    cfg = tmp_path / "surv.yaml"
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
    a = json.loads((ref / "summary.json").read_text())
    b = json.loads((out / "summary.json").read_text())
    assert b["completed"] is True and a["metrics"] == b["metrics"]
    ra, rb = load_arrays(ref / "arrays.npz"), load_arrays(out / "arrays.npz")
    for f in (*FIELDS, "track_rows"):
        np.testing.assert_array_equal(ra[f"{f}.spectral"], rb[f"{f}.spectral"], err_msg=f)
    net = json.loads((out / "network.json").read_text())
    assert net["rejected"] == {} and net["lost"] == 0
    assert_nothing_left(out)
    # the recording's scene (official reader): the cells shaded every scan, tracks by state
    from test_foxglove_up import SCENE, _visual

    scenes = _visual(out / "recording.mcap")[SCENE]
    assert len(scenes) == 10
    ids = [{e.id for e in s.entities} for s in scenes]
    assert all({f"cell/C{c}" for c in range(16)} <= i for i in ids)
    states = {kv.value for s in scenes for e in s.entities for kv in e.metadata
              if e.id.startswith("estimate/") and kv.key == "state"}  # fmt: skip
    assert "tentative" in states and "confirmed" in states
    rp = CovnetProcess(["replay", str(out)])
    assert rp.wait(timeout=120) == 0, rp.output()
    assert "identical" in rp.output()
