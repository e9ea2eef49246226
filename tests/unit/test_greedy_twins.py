"""Greedy on networks of repeated sensor models: of sensors with bit-identical gains only the
lowest-index copy not yet added is a forward candidate (the exact search's canonical twin).
Every copy was evaluated exactly at every step, to pick the one whose sum's rounding came out
least: 281 exact evaluations for 64 copies of the paper's 8 sensors, 16 of the 18 s of CPU of
one decision of a 1000-sensor network.  The values stay the plain heuristic's."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from covnet.core.allocation.exact import Constraints
from covnet.core.allocation.search import allocate_bnb, allocate_greedy
from covnet.covariance_control.bench_search import decision_problems, paper_gains, problem_scans

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "property"))
from test_greedy_reference import plain_greedy  # noqa: E402

G8 = paper_gains(8)
COPIES = np.concatenate([G8] * 8)  # 64 sensors: the paper's 8, eight times over


@pytest.mark.parametrize("metric", ["spectral", "kl", "trace_diff", "abs_trace"])
def test_copies_are_not_evaluated_one_by_one(metric):
    """A desired covariance far below reach: every sensor is added, one step each."""
    ((P, _),) = decision_problems(G8, "spectral", problem_scans(1))
    D = 1e-3 * np.eye(4)
    r = allocate_greedy(P, COPIES, D, metric)
    assert len(r.subset) == 64
    assert r.n_evaluated <= 8, r.n_evaluated  # was 281
    _, plain = plain_greedy(P, COPIES, D, metric, Constraints())
    assert r.value <= plain + 1e-9 * abs(plain)


@pytest.mark.parametrize("metric", ["spectral", "kl", "one_norm"])
def test_never_worse_than_plain_on_repeated_models(metric):
    for P, D in decision_problems(G8, metric, problem_scans(3)):
        _, plain = plain_greedy(P, COPIES, D, metric, Constraints())
        for r in (
            allocate_greedy(P, COPIES, D, metric),
            allocate_bnb(P, COPIES, D, metric, rel_gap=0.01, node_limit=2000),
        ):
            assert r.value <= plain + 1e-9 * abs(plain), (r.subset, r.value, plain)
