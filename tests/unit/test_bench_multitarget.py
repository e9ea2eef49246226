"""``covnet bench multitarget --search``: rows against the plain references where they run,
the goals stated, and a row that says why ``exact`` did not run instead of failing."""

from __future__ import annotations

import json

from covnet.cli.app import main
from covnet.covariance_control import bench_multitarget as bm


def test_rows_agree_with_the_references_and_state_the_goals():
    rows = bm.run((6,), (2,), ("kl",), ("exact", "bounded", "greedy"), n_problems=2,
                  exact_max=6, reference_assignments=3**6)  # fmt: skip
    assert [r["search"] for r in rows] == ["exact", "bounded", "greedy"]
    for r in rows:
        assert set(r) == set(bm.ROW_KEYS) and r["skipped"] is None
        assert r["exact_agree"] is True and r["reference_agree"] is True
        assert r["lower_bound_median"] <= r["value_median"]
        assert r["meets_gap"] == (r["gap_median"] <= bm.GAP_GOAL)
        assert r["meets_time"] is None and r["time_goal_s"] is None  # no goal at this size
    assert rows[0]["gap_median"] == 0.0 and rows[0]["excess_exact"] == 0.0
    assert bm.time_goal(64, 8) == 0.1 and bm.time_goal(256, 16) == 1.0


def test_exact_beyond_its_size_is_a_row_that_says_so(capsys):
    rows = bm.run((6,), (2,), ("kl",), ("exact",), n_problems=1, exact_max=4)
    assert len(rows) == 1 and "N = 6 > exact_max = 4" in rows[0]["skipped"]
    assert rows[0]["median_s"] is None
    args = ["bench", "multitarget", "--sensors", "64", "--targets", "1", "--search", "exact"]
    assert main([*args, "--metric", "kl", "--problems", "1", "--json"]) == 0
    (row,) = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert row["search"] == "exact" and "exact_max" in row["skipped"]


def test_a_network_that_covers_no_target_is_a_row_that_says_so(capsys):
    """One sensor whose range misses the target (the generated network at N = 1): every
    search's row is skipped with the reason, exit 0, instead of a traceback; a larger network
    of the same command decides."""
    args = ["bench", "multitarget", "--targets", "1", "--search", "bounded", "--search", "greedy"]
    assert main([*args, "--sensors", "1,3", "--metric", "kl", "--problems", "1", "--json"]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [(r["n_sensors"], r["search"]) for r in rows] == [
        (1, "bounded"), (1, "greedy"), (3, "bounded"), (3, "greedy"),
    ]  # fmt: skip
    for r in rows[:2]:
        assert "covers a target at 1 of the 1 decision scans" in r["skipped"]
        assert r["median_s"] is None and set(r) == set(bm.ROW_KEYS)
    for r in rows[2:]:
        assert r["skipped"] is None and r["lower_bound_median"] <= r["value_median"]


def test_the_cpu_clock_times_the_decisions_and_counts_the_bounded_limit(monkeypatch, capsys):
    """``--clock cpu``: the bounded search's 90 ms limit and the decisions' times count it
    (here a clock of 1 ms a reading: the same rows twice, in whole ticks, which the wall clock
    cannot promise)."""
    from covnet.covariance_control import bench_search as bs

    def rows():
        n = iter(range(10**9))
        monkeypatch.setitem(bs.CLOCKS, "cpu", lambda: next(n) * 1e-3)
        return bm.run((64,), (8,), ("abs_trace",), ("bounded",), n_problems=1, clock="cpu")

    (a,), (b,) = rows(), rows()
    assert a == b and a["clock"] == "cpu"
    assert a["median_s"] >= 0.09 and abs(a["median_s"] * 1e3 - round(a["median_s"] * 1e3)) < 1e-6
    args = ["bench", "multitarget", "--sensors", "16", "--targets", "3", "--search", "greedy"]
    assert main([*args, "--metric", "kl", "--problems", "1", "--clock", "cpu", "--json"]) == 0
    (row,) = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert row["clock"] == "cpu"
    assert main(["bench", "multitarget", "--clock", "cpu"]) == 2  # only with --search
    assert main(["bench", "alloc", "--clock", "cpu"]) == 2  # not a bench that takes it


def test_bounded_asks_for_the_tightest_certificate_its_limit_allows(monkeypatch):
    """The bench's bounded decisions run with ``rel_gap`` 0 (the row says so): the search's
    default stops at a gap of 1 % *of the value*, which is not the gap relative to the
    distance from doing nothing that several goals are judged in."""
    from covnet.core.allocation import assignment_search as srch

    seen = []
    real = srch.allocate_assignments_bounded

    def spy(*args, **kw):
        seen.append(kw.get("rel_gap"))
        return real(*args, **kw)

    monkeypatch.setattr(srch, "allocate_assignments_bounded", spy)
    rows = bm.run((6,), (2,), ("kl",), ("bounded", "greedy"), n_problems=2)
    assert seen == [0.0, 0.0] and bm.BOUNDED_REL_GAP == 0.0
    assert [(r["search"], r["rel_gap"]) for r in rows] == [("bounded", 0.0), ("greedy", None)]
