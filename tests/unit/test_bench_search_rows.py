"""``covnet bench search``'s rows say, per problem, how long each decision took and whether it
ended exact, so a capped run names the problems it left open."""

from __future__ import annotations

import numpy as np

import covnet.covariance_control.bench_search as bs


def test_per_problem_times_and_statuses_are_the_timed_calls(monkeypatch):
    seen: list[float] = []
    timed = bs._timed

    def spy(call, clock=bs.time.perf_counter):
        out = timed(call, clock)
        seen.append(out[1])
        return out

    monkeypatch.setattr(bs, "_timed", spy)
    (row,) = bs.run((10,), ["spectral"], ("exact",), n_problems=2, repeat=2,
                    exhaustive_max=0, plain_max=0)  # fmt: skip
    assert len(seen) == 4  # two timed calls a problem, in problem order
    assert row["problem_s"] == [float(np.median(seen[:2])), float(np.median(seen[2:]))]
    assert row["median_s"] == float(np.median(seen))
    assert row["problem_status"] == [0, 0] and row["n_exact"] == 2


def test_a_capped_exact_run_names_the_problems_it_left_open():
    (row,) = bs.run((24,), ["spectral"], ("exact",), n_problems=2, repeat=1, exact_cap_s=1e-4,
                    exhaustive_max=0, plain_max=0)  # fmt: skip
    assert row["problem_status"] == [2, 2] and row["n_exact"] == 0
    assert len(row["problem_s"]) == 2


class _Ticks:
    """A clock that advances ``step`` seconds at every reading, and counts them."""

    def __init__(self, step: float) -> None:
        self.step, self.n = step, 0

    def __call__(self) -> float:
        self.n += 1
        return self.n * self.step


def test_the_cpu_clock_times_the_decisions_and_counts_their_limits(monkeypatch):
    """``--clock cpu``: the decisions are timed by it and their caps count it (here a clock
    that jumps 1 s a reading: the exact search stops at its first look at the 0.5 s cap,
    which the wall clock would not reach at N = 12)."""
    ticks = _Ticks(1.0)
    monkeypatch.setitem(bs.CLOCKS, "cpu", ticks)
    kw = {"n_problems": 1, "repeat": 1, "exact_cap_s": 0.5, "exhaustive_max": 0, "plain_max": 0}
    (row,) = bs.run((12,), ["spectral"], ("exact",), clock="cpu", **kw)
    assert row["clock"] == "cpu" and row["problem_status"] == [2]
    assert row["median_s"] == float(round(row["median_s"])) >= 1.0  # whole ticks
    assert ticks.n > 4  # the search read it, not only the timer
    (wall,) = bs.run((12,), ["spectral"], ("exact",), **kw)
    assert wall["clock"] == "wall" and wall["problem_status"] == [0]


def test_covnet_bench_search_takes_the_cpu_clock(capsys):
    import json

    from covnet.cli.app import main

    args = ["bench", "search", "--sensors", "8", "--search", "greedy", "--metric", "kl"]
    assert main([*args, "--problems", "1", "--repeat", "1", "--clock", "cpu", "--json"]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [r["clock"] for r in rows] == ["cpu"]


def test_a_capped_exact_decision_is_checked_by_its_bounds_not_counted_as_a_disagreement(
    capsys, monkeypatch
):
    """``covnet bench search --search exact --exact-cap 0.001`` at N = 12 (where the
    exhaustive reference runs) exited 1, "a search disagreed with the exhaustive one": a
    decision its cap stopped is not claimed exact (``n_exact`` counts them).  Such a decision
    is held to what it does claim: its value at least the optimum, its bound at most it."""
    import dataclasses
    import json

    from covnet.cli.app import main

    args = ["bench", "search", "--sensors", "12", "--search", "exact", "--exact-cap", "1e-4"]
    assert main([*args, "--metric", "spectral", "--problems", "2", "--repeat", "1", "--json"]) == 0
    (row,) = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert row["n_exact"] == 0 and row["agree_exhaustive"] is True
    # a capped decision whose bound exceeds the optimum is a disagreement
    real = bs.allocate_bnb

    def too_high(*a, **k):
        r = real(*a, **k)
        return r if r.status == 0 else dataclasses.replace(r, lower_bound=r.value * 2.0 + 1.0)

    monkeypatch.setattr(bs, "allocate_bnb", too_high)
    (row,) = bs.run((12,), ["spectral"], ("exact",), n_problems=1, repeat=1, exact_cap_s=1e-4,
                    plain_max=0)  # fmt: skip
    assert row["n_exact"] == 0 and row["agree_exhaustive"] is False
