"""``covnet bench search``'s rows say, per problem, how long each decision took and whether it
ended exact, so a capped run names the problems it left open."""

from __future__ import annotations

import numpy as np

import covnet.covariance_control.bench_search as bs


def test_per_problem_times_and_statuses_are_the_timed_calls(monkeypatch):
    seen: list[float] = []
    timed = bs._timed

    def spy(call):
        out = timed(call)
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
