"""``configs/large.yaml`` (issue 17): 64 sensors on the paper's target, ``covnet run`` and
``covnet up`` in lockstep give the same results, the search's certified gaps included."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from multiproc import CovnetProcess, assert_nothing_left, assert_status_shows_gap, up_lockstep

from covnet.cli.app import main as covnet_main
from covnet.runs.rundir import load_arrays

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]

LARGE = Path(__file__).resolve().parents[2] / "configs" / "large.yaml"


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    out = tmp_path_factory.mktemp("ref") / "run"
    assert covnet_main(["run", str(LARGE), "--out", str(out), "--no-figures"]) == 0
    return out


@pytest.fixture(scope="module")
def lockstep_up(tmp_path_factory):
    out = tmp_path_factory.mktemp("up") / "run"
    return out, up_lockstep(LARGE, out)


def test_large_up_equals_run(reference, lockstep_up):
    out, _ = lockstep_up
    ref = json.loads((reference / "summary.json").read_text())
    got = json.loads((out / "summary.json").read_text())
    assert got["completed"] is True and len(got["sensor_ids"]) == 64
    assert got["metrics"] == ref["metrics"]  # subsets, values, lower bounds, gaps: all of it
    a_ref, a_got = load_arrays(reference / "arrays.npz"), load_arrays(out / "arrays.npz")
    for m in ref["metrics"]:
        for name in ("x_est", "P_post", "enabled", "value", "lower_bound", "gap"):
            assert np.array_equal(a_got[f"{name}.{m}"], a_ref[f"{name}.{m}"]), (m, name)
        blk = got["metrics"][m]
        assert len(blk["gap"]) == 100 and all(0.0 <= g <= 1.0 for g in blk["gap"])
        assert all(lb <= v for lb, v in zip(blk["lower_bound"], blk["value"], strict=True))


def test_large_up_lost_nothing_and_showed_the_gap(lockstep_up):
    out, output = lockstep_up
    net = json.loads((out / "network.json").read_text())
    assert net["rejected"] == {} and net["lost"] == 0
    # the live view shows each scan's certified gap (the manager's status: value, lower_bound,
    # gap, as live.json holds them while the run goes on)
    assert_status_shows_gap(output)
    assert_nothing_left(out)


def test_bench_up_sizes_against_the_probe(monkeypatch, capsys, paper_path):
    from covnet.bench import up as bench_up

    monkeypatch.setattr(bench_up, "SIZED_SCANS", 40)
    rc = covnet_main(
        ["bench", "up", "--sensors", "4,20", "--repeat", "1", "--json", "--config", str(paper_path)]
    )
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert rc == 0 and [r["n_sensors"] for r in rows] == [4, 20]
    assert [r["sensors_per_process"] for r in rows] == [1, bench_up.default_sensors_per_process(20)]
    for r in rows:
        assert r["scans"] == 40 and r["scans_per_s"] > 0 and r["probe_scans_per_s"] > 0
        assert r["ratio"] == r["scans_per_s"] / r["probe_scans_per_s"]
        assert r["ratio_threads"] == r["scans_per_s"] / r["probe_threads_scans_per_s"]
        assert 0 < r["probe_p50_ms"] <= r["probe_p99_ms"]


def test_the_probe_with_a_recording_tap_keeps_every_message():
    """The probe with a bare recording subscriber beside it (``taps=1``): it runs its scans and
    the tap keeps every message of the run, each command (and the stop) and every answer."""
    from covnet.bench.up import probe
    from covnet.bench.zenoh_probe import TAP_BURST_S
    from recorder.node import BATCH_S

    assert TAP_BURST_S == BATCH_S  # it drains as the recorder does
    n, scans = 6, 30
    out = probe(n, 3, scans, command_bytes=60, measurement_bytes=140, taps=1)
    assert out["scans"] == scans and out["scans_per_s"] > 0
    assert out["tap_messages"] == [scans * (1 + n) + 1]


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_256_sensors_become_ready_and_equal_run(tmp_path, paper_path):
    """256 sensors on the bus (four host processes of 64 on this machine's cores, each on one
    shared zenoh session): every node alive within ``network.ready_timeout_s``, the run
    complete and equal to the in-process run of the same config, nothing lost.  Three runs in a
    row (a second run right after a first was the one that most often missed the timeout)."""
    import yaml

    from covnet import kinds
    from covnet.covariance_control.network_sizes import bench_config

    _, sc = kinds.load(str(paper_path))
    cfg = tmp_path / "n256.yaml"
    cfg.write_text(yaml.safe_dump(bench_config(sc, 256, scans=30)))
    ref = tmp_path / "ref"
    assert covnet_main(["run", str(cfg), "--out", str(ref), "--no-figures"]) == 0
    want = json.loads((ref / "summary.json").read_text())["metrics"]
    for i in range(3):
        out = tmp_path / f"up-{i}"
        p = CovnetProcess(["up", str(cfg), "--out", str(out), "--no-figures"])
        try:
            rc = p.wait(timeout=180)
        finally:
            p.stop()
        assert rc == 0, f"run {i}:\n{p.output()}"
        got = json.loads((out / "summary.json").read_text())
        assert got["completed"] is True and got["metrics"] == want, f"run {i}"
        assert json.loads((out / "network.json").read_text())["lost"] == 0
        assert_nothing_left(out)


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_256_sensors_of_a_long_run_become_ready(tmp_path, paper_path):
    """256 sensors for 20 000 scans: every node alive within the default
    ``network.ready_timeout_s`` (30 s).  Each sensor drew the noise of every scan at start-up,
    and the manager gave up waiting for them after 30 s ("nodes not alive"); a sensor process
    now draws at most 400 000 at start-up (the rest as the scans come), each faster.  Stopped by a
    Ctrl-C once the scans run: nothing is left running."""
    import yaml

    from covnet import kinds
    from covnet.covariance_control.network_sizes import bench_config

    _, sc = kinds.load(str(paper_path))
    cfg = tmp_path / "n256-long.yaml"
    cfg.write_text(yaml.safe_dump(bench_config(sc, 256, scans=20_000)))
    out = tmp_path / "up"
    p = CovnetProcess(["up", str(cfg), "--out", str(out), "--no-figures"])
    try:
        ready = p.wait_for("[manager] READY", timeout=150)
        assert ready is not None, p.output()[-3000:]
        assert p.wait_for("/20000 256/256 on", timeout=60) is not None, p.output()[-3000:]
    finally:
        p.stop()
    assert "not alive" not in p.output()
    assert_nothing_left(out)


def test_bench_up_steady_measures_both_in_their_middle(capsys, paper_path):
    """``covnet bench up --sensors 4 --steady``: covnet's CPU a scan from every process of a
    real network in the middle of its run (by role), the probe's from a long run less a short
    one, and the budget's arithmetic on them."""
    from covnet.bench.budget import budget_row

    rc = covnet_main(
        ["bench", "up", "--sensors", "4", "--steady", "--repeat", "1", "--scans", "8000",
         "--json", "--config", str(paper_path)]
    )  # fmt: skip
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert rc == 0 and len(rows) == 1
    r = rows[0]
    assert r["n_sensors"] == 4 and r["scans"] == 8000 and 0 < r["window_scans"] < 8000
    assert set(r["cpu_ms_by_role"]) == {"manager", "world", "recorder", "sensors"}
    assert r["cpu_ms_per_scan"] == pytest.approx(sum(r["cpu_ms_by_role"].values()))
    assert r["cpu_ms_by_role"]["manager"] > 0 and r["cpu_ms_by_role"]["sensors"] > 0
    assert r["probe_cpu_ms_per_scan"] > 0 and r["probe_scans_per_s"] > 0
    assert 0 < r["cores"] <= 2.5  # this machine's two cores, and /proc's tick
    want = budget_row(
        {"cpu_ms_per_scan": r["cpu_ms_per_scan"], "scans_per_s": r["scans_per_s"]},
        {"cpu_ms_per_scan": r["probe_cpu_ms_per_scan"], "scans_per_s": r["probe_scans_per_s"]},
    )
    assert {k: r[k] for k in want} == want
