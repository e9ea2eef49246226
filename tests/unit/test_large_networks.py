"""Large networks (issue 17): the sized configs, the benchmarks' sensor counts, several sensors
in one process (:mod:`sensors.host`), the launcher's grouping."""

from __future__ import annotations

import argparse
import json
import threading
from pathlib import Path

import pytest

from covnet.cli.app import BENCH_SENSORS_MAX, build_parser, main
from covnet.covariance_control.config import from_dict, load
from covnet.covariance_control.network_sizes import bench_config, scaled_sensors
from covnet.processes.up import process_specs, sensor_hosts
from sensors.host import host

REPO = Path(__file__).resolve().parents[2]


def test_large_yaml_is_the_paper_scaled(paper):
    large = load(REPO / "configs" / "large.yaml")
    assert len(large.sensors) == 64
    spec = type(large.sensors[0])
    assert list(large.sensors) == [spec.model_validate(d) for d in scaled_sensors(paper, 64)]
    assert large.sensors[:8] == tuple(
        s.model_copy(update={"id": f"{s.id}.1"}) for s in paper.sensors
    )
    s8 = large.sensors[63]  # S8 at site 8: 2.75 times its sigmas
    assert (s8.id, s8.sigma_x_m, s8.rho) == ("S8.8", round(41.4 * 2.75, 3), -0.94)
    assert large.target == paper.target and large.desired == paper.desired
    assert large.allocation.search == "greedy"


def test_bench_config_enables_every_sensor(paper):
    sc = from_dict(bench_config(paper, 100, scans=20))
    assert len(sc.sensors) == 100 and set(sc.allocation.required) == set(sc.sensor_ids)
    assert sc.scans == 20 and sc.allocation.metrics == paper.allocation.metrics[:1]


def test_sensor_counts_per_benchmark(capsys):
    p = build_parser()
    assert p.parse_args(["bench", "search", "--sensors", "24,1000"]).sensors == [24, 1000]
    with pytest.raises(SystemExit):
        p.parse_args(["bench", "--sensors", "0,8"])
    assert "sensor counts must be >= 1" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        p.parse_args(["bench", "multitarget", "--targets", "3,0"])
    assert "argument --targets: target counts must be >= 1" in capsys.readouterr().err
    assert main(["bench", "alloc", "--sensors", "8,25"]) == 2
    assert f"takes counts up to {BENCH_SENSORS_MAX['alloc']}" in capsys.readouterr().err
    assert main(["bench", "multitarget", "--sensors", "17"]) == 2
    assert main(["bench", "mobile", "--sensors", "8"]) == 2
    assert "--sensors: bench mobile does not take this option" in capsys.readouterr().err
    assert main(["bench", "search", "--sensors", "8", "--exact-cap", "0"]) == 2


def test_bench_search_takes_a_thousand_sensors(capsys):
    rc = main(
        ["bench", "search", "--sensors", "1000", "--search", "greedy", "--metric", "abs_trace",
         "--problems", "1", "--repeat", "1", "--json"]
    )  # fmt: skip
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert rc == 0 and len(rows) == 1
    r = rows[0]
    assert (r["search"], r["n_sensors"]) == ("greedy", 1000)
    assert 0.0 <= r["gap_median"] <= r["gap_worst"] <= 1.0 and r["median_s"] > 0


def test_sensor_processes_host_their_groups(paper_path, paper, tmp_path):
    specs = process_specs(
        None,
        paper,
        str(paper_path),
        "r",
        "tcp/127.0.0.1:1",
        tmp_path,
        options={},
        realtime=False,
        speed=1.0,
        sensors_per_process=3,
    )
    sensors = [sp for sp in specs if sp.name.startswith("sensors@")]
    assert [sp.name for sp in sensors] == ["sensors@1", "sensors@2", "sensors@3"]
    ids = [sp.argv[i + 1] for sp in sensors for i, a in enumerate(sp.argv) if a == "--id"]
    assert ids == list(paper.sensor_ids)
    assert sensor_hosts(list(paper.sensor_ids), 8) == [("sensors@1", list(paper.sensor_ids))]


def _args(**kw) -> argparse.Namespace:
    return argparse.Namespace(id=None, run="r", **kw)


def test_host_runs_every_sensor_in_its_own_thread_with_its_own_args():
    seen: dict[str, tuple[str, bool]] = {}
    stop = threading.Event()

    def main_one(args, cfg, stop_):
        assert stop_ is stop and cfg == "cfg"
        seen[args.id] = (threading.current_thread().name, args.hosted)
        return 0

    assert host(["a", "b", "c"], main_one, _args(), "cfg", stop, share=False) == 0
    assert set(seen) == {"a", "b", "c"}
    assert len({name for name, _ in seen.values()}) == 3 and all(h for _, h in seen.values())
    assert not stop.is_set()


def test_a_failing_hosted_sensor_stops_the_host(capsys):
    stop = threading.Event()

    def main_one(args, cfg, stop_):
        if args.id == "bad":
            raise ConnectionError("authentication failed for bad")
        assert stop_.wait(10)  # the others are stopped by the failure
        return 0

    assert host(["ok1", "bad", "ok2"], main_one, _args(), None, stop, share=False) == 1
    err = capsys.readouterr().err
    assert "bad: error: authentication failed for bad" in err
    assert "hosted sensors failed: ['bad']" in err


def test_hosted_sensors_that_leave_with_a_failed_run_are_not_a_failure_of_their_own(capsys):
    """Sensors that left because the run did not end well give the process EXIT_RUN_FAILED
    (not restarted); a sensor's own failure among them outranks it."""
    from covnet.processes.process import EXIT_FAIL, EXIT_RUN_FAILED

    def leaving(args, cfg, stop_):
        return EXIT_RUN_FAILED if args.id != "fine" else 0

    assert host(["a", "fine", "b"], leaving, _args(), None, threading.Event(), share=False) == (
        EXIT_RUN_FAILED
    )
    assert "hosted sensors failed" not in capsys.readouterr().err

    def one_broken(args, cfg, stop_):
        if args.id == "bad":
            return EXIT_FAIL
        stop_.wait(10)
        return EXIT_RUN_FAILED

    assert host(["a", "bad", "b"], one_broken, _args(), None, threading.Event(), share=False) == (
        EXIT_FAIL
    )
    assert "hosted sensors failed: ['bad']" in capsys.readouterr().err


def test_sensors_process_refuses_unknown_or_repeated_ids(paper_path, capsys):
    from sensors.__main__ import main as sensors_main

    base = ["--config", str(paper_path), "--run", "r", "--connect", "tcp/127.0.0.1:1"]
    assert sensors_main([*base, "--id", "S1", "--id", "S9"]) == 2
    assert "'S9' is not in the config's sensors" in capsys.readouterr().err
    assert sensors_main([*base, "--id", "S1", "--id", "S1"]) == 2
    assert "named twice" in capsys.readouterr().err
