"""README "Adding a search", executed: a new search (plain forward selection: add the sensor that
lowers the metric most, while one does) is one :class:`~covnet.covariance_control.searches.\
Search` entry in ``SEARCHES`` (registered here in a temporary registry: the test's own
``monkeypatch``); a config naming it runs through ``covnet run``, a lockstep network run (equal
bit for bit) and ``covnet replay``; and the config refuses, in the entry's words, what it does
not use."""

from __future__ import annotations

import numpy as np
import pytest
from recipe_harness import run_all_three, write_config

from covnet.config import ConfigError
from covnet.core.allocation.exact import Allocation, subset_covariance
from covnet.core.metrics import get_metric
from covnet.covariance_control.config import load
from covnet.covariance_control.searches import SEARCHES, Search, feasible_count


def forward(model, P_pred, P_d, metric, c):
    """Forward selection from the required sensors: add the allowed sensor giving the smallest
    ``f(P(S + j), P_d)`` (lowest index among equals) while it lowers ``f`` and the budget allows.
    No bound: no certified gap."""
    CALLS.append(metric)
    f = get_metric(metric)
    G = model.gains
    N = len(model.sensor_ids)
    S = sorted(c.required)
    cap = N if c.max_active is None else c.max_active
    value = float(f(subset_covariance(P_pred, G[S].sum(axis=0)), P_d)) if S else np.inf
    n_eval = 1 if S else 0
    while len(S) < cap:
        best = None
        for j in range(N):
            if j in S or j in c.excluded:
                continue
            v = float(f(subset_covariance(P_pred, G[[*S, j]].sum(axis=0)), P_d))
            n_eval += 1
            if best is None or v < best[0]:
                best = (v, j)
        if best is None or not best[0] < value:
            break
        value, S = best[0], sorted([*S, best[1]])
    P = subset_covariance(P_pred, G[S].sum(axis=0))
    return Allocation(tuple(S), value, P, feasible_count(N, c), n_eval)


CALLS: list[str] = []
FORWARD = Search("forward", forward, "plain forward selection, no bound")


@pytest.fixture
def registered(monkeypatch):
    monkeypatch.setitem(SEARCHES, "forward", FORWARD)  # restored after the test


def test_a_new_search_runs_everywhere(registered, tmp_path):
    cfg = write_config(tmp_path, {"metrics": ["spectral"], "search": "forward"})
    CALLS.clear()
    run_all_three(cfg, tmp_path, "spectral")
    assert len(CALLS) == 3 * 20  # every scan of the three runs decided by the new entry


def test_the_config_accepts_it_only_while_registered(registered, tmp_path):
    cfg = write_config(tmp_path, {"search": "forward", "gap": 0.01})
    with pytest.raises(ConfigError) as err:
        load(cfg)
    assert ("allocation.gap", "only used with search: bounded or auto, not forward") in (
        err.value.problems
    )


def test_an_unregistered_search_is_refused(tmp_path):
    with pytest.raises(ConfigError) as err:
        load(write_config(tmp_path, {"search": "forward"}))
    assert any(p == "allocation.search" and "'greedy'" in m for p, m in err.value.problems)
