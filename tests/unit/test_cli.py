"""The ``covnet`` CLI end to end: run the paper scenario, check, plot, and user mistakes."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from covnet.cli import main
from covnet.covariance_control.plots import FIGURES
from covnet.rundir import load_arrays


@pytest.fixture(scope="module")
def paper_run(tmp_path_factory, paper_path):
    out = tmp_path_factory.mktemp("run") / "paper"
    assert main(["run", str(paper_path), "--out", str(out)]) == 0
    return out


def test_run_writes_complete_run_directory(paper_run):
    summary = json.loads((paper_run / "summary.json").read_text())
    assert summary["seed"] == 2026 and len(summary["config_hash"]) == 16
    assert set(summary["metrics"]) == {"spectral", "abs_trace", "svd"}
    for _m, blk in summary["metrics"].items():
        assert len(blk["sensors_per_scan"]) == 100
        assert len(blk["subsets"]) == 100 and len(blk["P_diag"]) == 100
        assert all(len(d) == 4 for d in blk["P_diag"])
        assert [len(s) for s in blk["subsets"]] == blk["sensors_per_scan"]
        assert blk["allocation_rate"] == pytest.approx(sum(blk["sensors_per_scan"]) / 800)
        assert np.isfinite(blk["rmse_position"]) and blk["rmse_position"] > 0
    arrays = load_arrays(paper_run / "arrays.npz")
    assert arrays["truth"].shape == (100, 4)
    assert arrays["x_est.svd"].shape == (100, 4)
    assert arrays["P_post.spectral"].shape == (100, 4, 4)
    assert arrays["enabled.abs_trace"].shape == (100, 8)
    # summary and arrays tell the same story
    en = arrays["enabled.spectral"]
    assert en.sum(axis=1).tolist() == summary["metrics"]["spectral"]["sensors_per_scan"]
    np.testing.assert_allclose(
        np.diagonal(arrays["P_post.svd"], axis1=1, axis2=2), summary["metrics"]["svd"]["P_diag"]
    )
    for f in FIGURES:
        assert (paper_run / f).stat().st_size > 10_000, f


def test_run_single_metric_and_seed_override(tmp_path, paper_path):
    out = tmp_path / "one"
    assert (
        main(
            [
                "run",
                str(paper_path),
                "--out",
                str(out),
                "--metric",
                "kl",
                "--seed",
                "5",
                "--no-figures",
            ]
        )
        == 0
    )
    summary = json.loads((out / "summary.json").read_text())
    assert list(summary["metrics"]) == ["kl"] and summary["seed"] == 5


def test_refuses_to_overwrite_a_run(paper_run, paper_path, capsys):
    assert main(["run", str(paper_path), "--out", str(paper_run)]) == 2
    assert "--force" in capsys.readouterr().err
    assert (paper_run / "summary.json").is_file()


def test_unknown_metric_is_a_usage_error(tmp_path, paper_path, capsys):
    assert main(["run", str(paper_path), "--out", str(tmp_path / "x"), "--metric", "nope"]) == 2
    err = capsys.readouterr().err
    assert "unknown metric 'nope'" in err and "spectral" in err


def test_bad_config_exits_2_with_path_and_no_traceback(tmp_path, paper_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text(paper_path.read_text().replace("rho: 0.78}", "rho: 1.78}"))
    proc = subprocess.run(
        [sys.executable, "-m", "covnet", "run", str(bad), "--out", str(tmp_path / "o")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    assert "sensors[2].rho: must be in (-1, 1)" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "o").exists()


def test_check_prints_normalised_config_and_hash(paper_path, capsys):
    assert main(["check", str(paper_path)]) == 0
    out = capsys.readouterr().out
    assert "# config hash: " in out and "sigma_x_m: 21.1" in out


def test_plot_redraws_from_files(paper_run, capsys):
    for f in FIGURES:
        (paper_run / f).unlink()
    assert main(["plot", str(paper_run)]) == 0
    assert all((paper_run / f).is_file() for f in FIGURES)


def test_plot_on_incomplete_directory(tmp_path, capsys):
    assert main(["plot", str(tmp_path)]) == 2
    assert "not a complete run directory" in capsys.readouterr().err


def test_bench_json_rows(paper_path, capsys):
    rc = main(
        [
            "bench",
            "--sensors",
            "4,6",
            "--metric",
            "abs_trace",
            "--metric",
            "spectral",
            "--problems",
            "2",
            "--repeat",
            "1",
            "--json",
            "--config",
            str(paper_path),
        ]
    )
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert rc == 0
    assert {(r["metric"], r["n_sensors"]) for r in rows} == {
        (m, n) for m in ("abs_trace", "spectral") for n in (4, 6)
    }
    for r in rows:
        assert set(r) >= {"metric", "n_sensors", "median_s", "baseline_median_s", "peak_mb"}
        assert r["median_s"] > 0 and r["baseline_median_s"] > 0 and r["agree"]


def test_bench_rejects_bad_sensor_list(capsys):
    with pytest.raises(SystemExit) as info:
        main(["bench", "--sensors", "8,x"])
    assert info.value.code == 2
    assert "comma-separated integers" in capsys.readouterr().err


@pytest.mark.parametrize("target", ["mobile", "passive"])
def test_bench_routes_to_the_scenario_benchmarks(monkeypatch, target):
    import importlib

    mod = importlib.import_module(f"covnet.{target}.commands")
    calls = []
    monkeypatch.setattr(mod, "bench_run", lambda json_out, **kw: calls.append(json_out) or 0)
    assert main(["bench", target, "--json"]) == 0
    assert calls == [True]


@pytest.mark.parametrize("name", ["mobile", "passive"])
def test_check_validates_every_scenario_kind(name, capsys):
    from pathlib import Path

    cfg = Path(__file__).resolve().parents[2] / "configs" / f"{name}.yaml"
    assert main(["check", str(cfg)]) == 0
    out = capsys.readouterr().out
    assert f"kind: {name}" in out and "# config hash: " in out


def test_bench_fusion_json_rows(capsys):
    assert main(["bench", "fusion", "--sensors", "4", "--json"]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert {r["objective"] for r in rows} == {"det", "trace", "fast"}
    for r in rows:
        assert r["n_sensors"] == 4 and r["n_subsets"] == 15 and r["median_s"] > 0


def test_a_failed_bench_network_run_says_why_without_a_traceback(monkeypatch, capsys):
    """bench up: a network run that fails ends the command with its reason and the run's
    output, exit 1 (UpError), not a traceback."""
    from covnet import bench_up
    from covnet.errors import UpError

    def failing_up(*args, **kwargs):
        print("[manager] manager: error: nodes not alive after 30.0 s: ['S1']")
        raise UpError("the manager exited with status 1 before READY")

    monkeypatch.setattr(bench_up, "up", failing_up)
    assert main(["bench", "up", "--repeat", "1"]) == 1
    err = capsys.readouterr().err
    assert "the manager exited with status 1 before READY" in err
    assert "nodes not alive after 30.0 s: ['S1']" in err
    assert "Traceback" not in err


def test_a_reader_that_closes_the_pipe_stops_covnet_quietly(paper_path):
    """``covnet check CONFIG | head -1``: no traceback, the status of a tool SIGPIPE stopped
    (141); a BrokenPipeError that is not stdout's is not taken for it (stdout still open)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "covnet", "check", str(paper_path)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    assert proc.stdout is not None and proc.stderr is not None
    first = proc.stdout.readline()
    proc.stdout.close()  # the reader goes away after one line
    err = proc.stderr.read().decode()
    proc.stderr.close()
    assert proc.wait(timeout=60) == 141, err
    assert first.startswith(b"kind:") and "Traceback" not in err and "Broken" not in err


def test_a_broken_pipe_that_is_not_stdouts_is_not_hidden(monkeypatch, paper_path):
    import covnet.cli as cli

    def broken(args):
        raise BrokenPipeError(32, "a child's pipe")

    monkeypatch.setattr(cli, "cmd_check", broken)
    with pytest.raises(BrokenPipeError):
        main(["check", str(paper_path)])


@pytest.mark.parametrize("done", [{}, {"spectral": 0, "svd": 0}, 0])
@pytest.mark.parametrize("status", ["interrupted", "failed"])
def test_replay_of_a_run_that_ended_before_its_first_scan_says_so(tmp_path, capsys, status, done):
    """Ctrl-C before READY: a run directory with no scan (and, often, no recording): replay
    says there is nothing to replay (exit 2), whether or not a recording was started."""
    (tmp_path / "config.json").write_text("{}")
    (tmp_path / "recording.mcap").write_bytes(b"")
    info = {"status": status, "ended": "stopped before the network was ready"}
    (tmp_path / "run.json").write_text(json.dumps({**info, "scans_completed": done}))
    assert main(["replay", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "nothing to replay: the run ended before its first scan" in err, err
    assert f"status {status}" in err and "stopped before the network was ready" in err, err
