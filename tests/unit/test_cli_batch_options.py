"""Batch options a command cannot honour are refused, not ignored: ``covnet mc`` of a
covariance-control config refuses ``--max-seeds`` as it refuses ``--ci-width`` (the cap only
bounds what ``--ci-width`` adds); ``covnet plot --point`` on a run or mc directory says that
per-point curves belong to sweep and compare directories; a seed count above ``MAX_SEEDS`` is
refused while the options are parsed, before a directory is made (a batch lists its runs
before it starts: ``--seeds 99999999999999999999`` filled the memory); the API's ``sweep``
checks its batch arguments as the command does."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from covnet.cli.app import MAX_SEEDS, main


@pytest.fixture(scope="module")
def paper5(tmp_path_factory, paper_path):
    data = yaml.safe_load(paper_path.read_text())
    data["scans"] = 5
    path = tmp_path_factory.mktemp("cfg") / "paper5.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_covariance_control_mc_refuses_max_seeds(paper5, tmp_path, capsys):
    out = tmp_path / "mc"
    assert main(["mc", str(paper5), "--trials", "2", "--max-seeds", "5", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "--max-seeds" in err and "--trials seeds" in err and "Traceback" not in err
    assert not out.exists()


def test_plot_point_on_a_run_or_mc_directory_is_refused(paper5, tmp_path, capsys):
    run, mc = tmp_path / "run", tmp_path / "mc"
    args = ["--metric", "spectral", "--no-figures"]
    assert main(["run", str(paper5), "--out", str(run), *args]) == 0
    assert main(["mc", str(paper5), "--trials", "2", "--out", str(mc), "--no-figures"]) == 0
    capsys.readouterr()
    for d, what in ((run, "a run directory"), (mc, "a covnet mc directory")):
        assert main(["plot", str(d), "--point", "delay_ms=350"]) == 2
        err = capsys.readouterr().err
        assert f"--point: {d} is {what}" in err and "sweep and covnet compare" in err
    assert main(["plot", str(run)]) == 0  # without --point it draws


@pytest.mark.parametrize(
    "argv",
    [
        ["mc", "{cfg}", "--trials", "{n}"],
        ["mc", "{cfg}", "--seeds", "{n}"],
        ["compare", "{cfg}", "--runs", "{n}"],
        ["sweep", "{cfg}", "--seeds", "{n}"],
        ["sweep", "{cfg}", "--ci-width", "1", "--max-seeds", "{n}"],
    ],
)
def test_a_seed_count_above_the_limit_is_refused_before_anything_runs(
    argv, paper5, tmp_path, capsys
):
    out = tmp_path / "out"
    n = 99999999999999999999
    args = [a.format(cfg=paper5, n=n) for a in argv] + ["--out", str(out)]
    with pytest.raises(SystemExit) as exc:
        main(args)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert f"at most {MAX_SEEDS} in one batch, got {n}" in err and "Traceback" not in err
    assert not out.exists()


@pytest.mark.parametrize(
    "argv",
    [
        ["bench", "search", "--sensors", "12", "--problems", "99999999999999999999"],
        ["bench", "multitarget", "--sensors", "16", "--targets", "3", "--problems", "20000"],
        ["bench", "search", "--sensors", "12", "--repeat", "99999999999999999999"],
    ],
)
def test_bench_counts_above_the_limit_are_named(argv, capsys):
    """They failed in numpy with a traceback (``Maximum allowed size exceeded``)."""
    from covnet.cli.bench_commands import BENCH_COUNT_MAX

    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"at most {BENCH_COUNT_MAX}, got" in err and "Traceback" not in err


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"seeds": -3}, "seeds: an integer from 1 to"),
        ({"seeds": 99999999999999999999}, "seeds: an integer from 1 to"),
        ({"seeds": 2, "workers": 0}, "workers: must be >= 1, got 0"),
        ({"seeds": 2, "ci_width": -1.0}, "ci_width: must be a width > 0"),
        ({"seeds": 2, "max_seeds": 5}, "max_seeds: caps the seeds ci_width adds"),
        ({"seeds": 2, "ci_width": 1.0, "max_seeds": 10**9}, "max_seeds: at most"),
        ({"seeds": 2, "cluster": "nowhere"}, "cluster: a Dask scheduler address"),
    ],
)
def test_the_api_sweep_checks_its_batch_arguments_as_the_command(kwargs, message, tmp_path):
    """``covnet.api.sweep`` ran with ``seeds=-3`` (no run at all), ``workers=0`` or
    ``ci_width=-1`` and filled the memory with ``seeds=10**20``; it now refuses them, naming
    its own parameters, before a directory is made."""
    from covnet import api
    from covnet.errors import UsageError

    out = tmp_path / "sweep"
    grid = {"delay_ms": [0], "loss": [0.0], "modes": ["central"], "account_for_loss": [False]}
    latency = Path(__file__).resolve().parents[2] / "configs" / "latency.yaml"
    with pytest.raises(UsageError, match=message):
        api.sweep(str(latency), out=out, **grid, **kwargs)
    assert not out.exists()


def test_compare_modes_named_twice_are_refused_as_policies_are(paper5, tmp_path, capsys):
    """``--modes central,central`` ran the mode twice and printed two identical rows."""
    out = tmp_path / "cmp"
    argv = ["compare", str(paper5), "--runs", "2", "--modes", "central,ci,central"]
    assert main([*argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "--modes: central named twice" in err and "Traceback" not in err
    assert not out.exists()


@pytest.mark.parametrize("cmd", ["compare", "sweep"])
def test_two_metrics_for_a_one_metric_batch_are_refused(cmd, paper5, tmp_path, capsys):
    """``covnet sweep --metric kl --metric spectral`` ran spectral alone (the last), saying
    nothing of kl; the same metric twice is still one."""
    out = tmp_path / "b"
    cfg = str(paper5)
    seeds = ["--runs", "2"] if cmd == "compare" else ["--seeds", "1"]
    argv = [cmd, cfg, *seeds, "--metric", "kl", "--metric", "spectral", "--out", str(out)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "--metric: this command compares with one metric, got kl, spectral" in err
    assert not out.exists()


@pytest.mark.parametrize(
    ("opt", "value", "message"),
    [
        ("--realtime-s", "inf", "--realtime-s: must be a finite number, got inf"),
        ("--realtime-s", "nan", "--realtime-s: must be >= 0, got nan"),
        ("--windows", "99999999999", "--windows: at most 10000, got 99999999999"),
        ("--interval", "inf", "--interval: must be a finite number > 0, got inf"),
        ("--speed", "inf", "--speed: must be a finite number > 0, got inf"),
    ],
)
def test_bench_soak_names_values_it_cannot_use(opt, value, message, capsys):
    """``--realtime-s inf`` and ``nan`` ended in an OverflowError or ValueError traceback,
    ``--windows 99999999999`` in a MemoryError, and ``--interval inf`` ran without ever
    sampling."""
    assert main(["bench", "soak", opt, value]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


@pytest.mark.parametrize("what", ["a file", "an earlier soak's"])
def test_bench_soak_work_must_be_new_or_empty(tmp_path, capsys, what):
    """``--work`` of an earlier soak failed after the set-up, exit 1, with its lockstep run's
    --out message; a file, with "File exists".  Now named first, exit 2."""
    work = tmp_path / "w"
    if what == "a file":
        work.write_text("x")
        message = f"--work {work}: exists and is not a directory"
    else:
        (work / "lockstep").mkdir(parents=True)
        (work / "soak-5.yaml").write_text("x")
        message = f"--work {work}: not empty"
    argv = ["bench", "soak", "--scans", "5", "--realtime-s", "0", "--work", str(work)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
