"""The ``covnet`` CLI end to end: run the paper scenario, check, plot, and user mistakes."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import numpy as np
import pytest

from covnet.cli.app import main
from covnet.covariance_control.plots import FIGURES
from covnet.runs.rundir import load_arrays


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
    from covnet.bench import up as bench_up
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


@pytest.mark.parametrize("unbuffered", ["1", ""])
def test_a_reader_that_closes_the_pipe_stops_covnet_quietly(paper_path, unbuffered):
    """``covnet check CONFIG | true``: the reader is gone before covnet writes (its end of
    the pipe closed before covnet starts, so no timing decides it): no traceback, no
    "Exception ignored", the status of a tool SIGPIPE stopped (141), whether stdout is
    written through (``PYTHONUNBUFFERED``) or only flushed at the end."""
    import os

    read_end, write_end = os.pipe()
    os.close(read_end)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
    if unbuffered:
        env["PYTHONUNBUFFERED"] = unbuffered
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "covnet", "check", str(paper_path)],
            stdout=write_end,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
            timeout=60,
        )
    finally:
        os.close(write_end)
    err = proc.stderr
    assert proc.returncode == 141, err
    assert "Traceback" not in err and "Broken" not in err and "Exception ignored" not in err


def test_a_broken_pipe_that_is_not_stdouts_is_not_hidden(monkeypatch, paper_path):
    import covnet.cli.app as cli

    def broken(args):
        raise BrokenPipeError(32, "a child's pipe")

    monkeypatch.setattr(cli, "cmd_check", broken)
    with pytest.raises(BrokenPipeError):
        main(["check", str(paper_path)])


def _target_block(rmse: float, max_err: float, nees: float) -> dict:
    return {
        "rmse_position": rmse,
        "max_position_error": max_err,
        "mean_nees": nees,
        "nees_band_95": [3.6, 4.4],
        "mean_nis": 2.0,
        "sensors_per_scan": [2, 2],
    }


def test_run_summary_says_a_track_was_lost_and_the_search_gap(tmp_path, capsys):
    """covnet run's printout names a target whose track was lost (mc's criterion: ever
    further from the truth than the OSPA cut-off) and a bounded or greedy search's gap."""
    from covnet.covariance_control.commands import print_summary

    targets = {
        "config_hash": "abc",
        "seed": 1,
        "association": "gnn",
        "target_ids": ["T1", "T2"],
        "ospa": {"cutoff_m": 100.0, "order": 1},
        "metrics": {
            "spectral": {
                "allocation_rate": 0.5,
                "mean_ospa": 50.0,
                "mean_gospa": 60.0,
                "targets": {
                    "T1": _target_block(234.0, 612.0, 562.0),
                    "T2": _target_block(12.0, 40.0, 4.1),
                },
            }
        },
    }
    print_summary(tmp_path, targets)
    lines = capsys.readouterr().out.splitlines()
    t1 = next(line for line in lines if "T1:" in line)
    t2 = next(line for line in lines if "T2:" in line)
    assert "track lost" in t1 and "612" in t1 and "100" in t1
    assert "lost" not in t2
    single = {
        "config_hash": "abc",
        "seed": 1,
        "metrics": {
            "spectral": {
                "allocation_rate": 0.5,
                "rmse_position": 20.0,
                "mean_nees": 4.0,
                "gap_median": 0.0012,
                "gap_worst": 0.05,
            },
            "abs_trace": {
                "allocation_rate": 0.5,
                "rmse_position": 20.0,
                "mean_nees": 4.0,
                "gap_median": 0.25,
                "gap_worst": 1.0,
                "gap_nothing_median": 0.0062,
                "gap_nothing_worst": 0.0123,
            },
            "svd": {"allocation_rate": 0.5, "rmse_position": 20.0, "mean_nees": 4.0},
            "kl": {
                "allocation_rate": 0.5,
                "rmse_position": 20.0,
                "mean_nees": 4.0,
                "gap_median": None,
                "gap_worst": None,
            },
        },
    }
    print_summary(tmp_path, single)
    out = capsys.readouterr().out.splitlines()
    spectral = next(line for line in out if "spectral:" in line)
    assert "search gap median 0.12 %, worst 5.00 %" in spectral
    assert "doing nothing" not in spectral  # a summary without the second measure
    abs_trace = next(line for line in out if "abs_trace:" in line)
    assert (
        "search gap median 25.00 %, worst 100.00 % (of the distance from doing nothing: "
        "median 0.62 %, worst 1.23 %)" in abs_trace
    )
    assert "gap" not in next(line for line in out if "svd:" in line)
    assert "search gap not reported" in next(line for line in out if "kl:" in line)


@pytest.mark.parametrize("command", ["mc", "compare", "sweep", "bench"])
def test_help_says_json_is_json_lines(command, capsys):
    with pytest.raises(SystemExit) as info:
        main([command, "--help"])
    assert info.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    assert re.search(r"--json (\[[^]]*\] )?JSON Lines", text), text


def test_covnet_help_names_every_benchmark(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "'soak'" in text and "'cluster'" in text


@pytest.mark.parametrize(
    ("argv", "refused"),
    [
        (["bench", "alloc", "--search", "greedy", "--targets", "5"], "--search"),
        (["bench", "--targets", "5"], "--targets"),
        (["bench", "fusion", "--problems", "2"], "--problems"),
        (["bench", "mobile", "--sensors", "8"], "--sensors"),
        (["bench", "cluster", "--scans", "10"], "--scans"),
        (["bench", "soak", "--foxglove"], "--foxglove"),
    ],
)
def test_a_bench_option_that_does_not_apply_is_refused(argv, refused, capsys):
    """Every option given to a benchmark that does not take it: exit 2, a message naming it
    and the benchmark's own options (it was silently ignored)."""
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert (
        f"{refused}: bench {argv[1] if len(argv) > 1 and not argv[1].startswith('-') else 'alloc'}"
        in err
    )
    assert "does not take this option" in err and "Traceback" not in err


@pytest.mark.parametrize(
    "argv, message",
    [
        # exact above 40 sensors gave no row and exit 0
        (["bench", "search", "--search", "exact", "--sensors", "20,41"], "--search exact: bench"),
        # without --sensors the paper network ran as covnet up hosts it, K unused
        (["bench", "up", "--sensors-per-process", "4"], "--sensors-per-process: only with"),
        # --repeat 1 ran 2 pairs
        (["bench", "cluster", "--repeat", "1"], "--repeat: bench cluster alternates"),
    ],
)
def test_a_bench_option_that_would_have_no_effect_is_refused(argv, message, capsys):
    """An option a benchmark takes but could not honour is refused before anything runs (exit
    2, one line), not silently dropped."""
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


def test_bench_help_says_which_benchmarks_take_each_option(capsys):
    with pytest.raises(SystemExit):
        main(["bench", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--targets T,T,... [multitarget]" in text
    assert "--scans SCANS [up, soak]" in text
    assert "--steady [up]" in text


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


@pytest.mark.parametrize("before", [[], ["processes.json"]])
def test_up_stopped_before_anything_was_written_says_so_and_replay_too(tmp_path, capsys, before):
    """``covnet up`` interrupted before the manager wrote its config: the directory was left
    empty (or with the process list) without a run.json, the launcher said it held the process
    list, and ``covnet replay`` answered "not a recorded network run directory"."""
    from covnet.processes.up import settle

    for name in before:
        (tmp_path / name).write_text("[]")
    said = settle(None, None, tmp_path, {}, "interrupted", "stopped before the network was ready")
    assert said == f"nothing was recorded ({tmp_path} holds no results)"
    info = json.loads((tmp_path / "run.json").read_text())
    assert info["status"] == "interrupted" and info["scans_completed"] == 0
    assert main(["replay", str(tmp_path)]) == 2
    assert "nothing to replay: the run ended before its first scan" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("argv", "dest"),
    [
        (["mc", "c.yaml", "--seeds", "7"], "trials"),
        (["mc", "c.yaml", "--trials", "7"], "trials"),
        (["compare", "c.yaml", "--seeds", "7"], "runs"),
        (["compare", "c.yaml", "--runs", "7"], "runs"),
        (["sweep", "c.yaml", "--seeds", "7"], "seeds"),
    ],
)
def test_every_batch_command_takes_seeds(argv, dest):
    """mc (--trials), compare (--runs) and sweep (--seeds) count their seeds under three names;
    each takes --seeds too, the same option (``--seeds 2`` was 'unrecognized' by mc and
    compare), and mc's --seed stays the first seed."""
    from covnet.cli.app import build_parser

    args = build_parser().parse_args(argv)
    assert getattr(args, dest) == 7
    args = build_parser().parse_args(["mc", "c.yaml", "--seeds", "3", "--seed", "11"])
    assert (args.trials, args.seed) == (3, 11)


def test_mc_with_seeds_is_mc_with_trials(tmp_path, paper_path, capsys):
    outs = []
    for opt in ("--seeds", "--trials"):
        out = tmp_path / opt.strip("-")
        argv = ["mc", str(paper_path), opt, "2", "--metric", "spectral", "--workers", "1"]
        assert main([*argv, "--out", str(out), "--no-figures"]) == 0
        outs.append(out)
    a, b = (json.loads((o / "montecarlo.json").read_text()) for o in outs)
    assert a == b and a["seeds"] == [2026, 2027]
