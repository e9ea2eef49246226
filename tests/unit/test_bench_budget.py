"""``covnet bench up --steady`` (:mod:`covnet.bench.budget`): the steady window, the budget's
arithmetic and the options it takes."""

from __future__ import annotations

import pytest

from covnet.bench.budget import budget_row, steady_window
from covnet.cli.app import main as covnet_main
from covnet.errors import UpError


def test_the_window_is_the_middle_samples_difference():
    samples = [
        (100, {"manager": 1.0, "sensors": 2.0}),  # before a third of 900: start-up
        (310, {"manager": 1.5, "sensors": 3.0}),
        (600, {"manager": 2.5, "sensors": 4.0, "recorder": 0.5}),
        (800, {"manager": 3.1, "sensors": 5.0, "recorder": 0.9}),
        (900, {"manager": 9.0, "sensors": 9.0, "recorder": 9.0}),  # the last scan: the end
    ]
    n, by = steady_window(samples, 900)
    assert n == 490
    assert by == pytest.approx({"manager": 1.6, "sensors": 2.0, "recorder": 0.9})


def test_a_run_too_short_for_two_middle_samples_is_refused():
    with pytest.raises(UpError, match="--scans"):
        steady_window([(50, {}), (400, {"manager": 1.0}), (600, {"manager": 2.0})], 600)


def test_the_budget_is_the_cores_used_at_one_half_of_the_probe():
    covnet = {"cpu_ms_per_scan": 6.0, "scans_per_s": 250.0}
    probe = {"cpu_ms_per_scan": 1.5, "scans_per_s": 700.0}
    row = budget_row(covnet, probe)
    assert row["cores"] == pytest.approx(1.5) and row["probe_cores"] == pytest.approx(1.05)
    assert row["ratio"] == pytest.approx(250 / 700)
    assert row["budget_ms_per_scan"] == pytest.approx(1e3 * 1.5 / 350)  # 4.29 ms
    assert row["cut_needed"] == pytest.approx(1 - (1e3 * 1.5 / 350) / 6.0)
    fast = budget_row({"cpu_ms_per_scan": 2.0, "scans_per_s": 400.0}, probe)
    assert fast["cut_needed"] == 0.0  # above one half already


@pytest.mark.parametrize(
    "argv, said",
    [
        (["bench", "up", "--steady"], "--steady: only with --sensors"),
        (["bench", "up", "--scans", "100"], "--scans: only with --sensors"),
        (
            ["bench", "up", "--sensors", "4", "--scans", "100"],
            "--scans: bench up takes it with --steady",
        ),
        (["bench", "search", "--steady"], "--steady: bench search does not take this option"),
    ],
)
def test_bench_up_steady_options_are_checked(argv, said, capsys, monkeypatch, paper_path):
    monkeypatch.chdir(paper_path.parents[1])
    assert covnet_main(argv) == 2
    assert said in capsys.readouterr().err
