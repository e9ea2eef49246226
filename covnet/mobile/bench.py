"""Benchmark of one mobile decision: cost tensor and solvers over problem sizes (spec §8.2).

Random single decisions with ``N`` sensors and ``M`` targets, capacity none and
``K = ⌈1.5 M / N⌉`` for every sensor.  Instances: sensors and targets uniform in a square whose
side grows as ``300 m · sqrt(N / 4)`` (the density of the ``mobile`` scenario), speeds
``U(2, 3)`` m/s, ``σ0 ~ U(2, 3)`` m, ``b0 ~ U(0.8, 1.2)``, target velocities ``U(−1, 1)`` m/s,
``P⁻ = diag(25, 0.25, 25, 0.25) · U(0.2, 2)``; the generator is ``default_rng([2026, N, M, p])``
for problem ``p``.

Per (N, M, capacity), medians in ms over problems × repeats:

* ``cost``: the cost tensor;
* ``lp``: the configured-default solver ``lp`` (closed form without capacity, HiGHS with);
* ``decision``: cost tensor + ``lp``, timed together (the goal: < 50 ms at 50 × 100 with
  capacity);
* ``closed_form``: the closed form alone (no capacity only; goal < 2 ms at 50 × 100);
* ``lp_highs``: the LP by HiGHS dual simplex (also without capacity, for the comparison);
* ``milp``: the exact MILP, strong linking, once per problem (``milp=False`` skips it);
* ``worse``: in how many problems the LP + post-step was worse than the MILP, and the max gap.

The machine is shared and noisy: compare ratios within one run, not across runs.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from functools import partial
from typing import Any

import numpy as np

from covnet.core.mobile.cost import CostParams, cost_tensor
from covnet.core.mobile.decision import (
    Decision,
    DecisionProblem,
    SolverOptions,
    decide_closed_form,
    decide_lp,
    decide_lp_highs,
    decide_milp,
)
from covnet.core.mobile.models import Sensors

SENSORS = (4, 10, 25, 50)
TARGETS = (3, 10, 30, 100)
GOAL_DECISION_MS = 50.0
GOAL_CLOSED_FORM_MS = 2.0


def random_instance(
    N: int, M: int, problem: int, capacity: int | None
) -> tuple[np.ndarray, np.ndarray, Sensors]:
    """Predicted tracks ``(x⁻, P⁻)`` and sensors of one random decision (module docstring)."""
    rng = np.random.default_rng([2026, N, M, problem])
    side = 300.0 * math.sqrt(N / 4.0)
    sensors = Sensors(
        position=rng.uniform(0.0, side, (N, 2)),
        speed=rng.uniform(2.0, 3.0, N),
        R0=rng.uniform(2.0, 3.0, N)[:, None, None] ** 2 * np.eye(2),
        r_pd=np.full(N, 60.0),
        b0=rng.uniform(0.8, 1.2, N),
        b1=np.zeros(N),
        capacity=np.full(N, np.inf if capacity is None else float(capacity)),
    )
    x = np.empty((M, 4))
    x[:, [0, 2]] = rng.uniform(0.0, side, (M, 2))
    x[:, [1, 3]] = rng.uniform(-1.0, 1.0, (M, 2))
    P = np.diag([25.0, 0.25, 25.0, 0.25])[None] * rng.uniform(0.2, 2.0, M)[:, None, None]
    return x, P, sensors


def _median_ms(fn: Callable[[], object], repeat: int) -> float:
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(ts))


def _whole(x: np.ndarray, P: np.ndarray, sensors: Sensors, params: CostParams) -> Decision:
    """One whole decision: the cost tensor, then the ``lp`` solver."""
    ct = cost_tensor(x, P, sensors, params)
    return decide_lp(DecisionProblem(ct.c, ct.c0, sensors.capacity))


def bench_case(
    N: int, M: int, capacity: int | None, problems: int, repeat: int, milp: bool
) -> dict[str, Any]:
    """One row of the table (see the module docstring)."""
    params = CostParams()
    t: dict[str, list[float]] = {
        k: [] for k in ("cost", "lp", "decision", "closed_form", "lp_highs", "milp")
    }
    worse, max_gap = 0, 0.0
    for p in range(problems):
        x, P, sensors = random_instance(N, M, p, capacity)
        ct = cost_tensor(x, P, sensors, params)
        prob = DecisionProblem(ct.c, ct.c0, sensors.capacity)
        _whole(x, P, sensors, params)  # warm-up (imports, caches)
        t["cost"].append(_median_ms(partial(cost_tensor, x, P, sensors, params), repeat))
        t["lp"].append(_median_ms(partial(decide_lp, prob), repeat))
        t["decision"].append(_median_ms(partial(_whole, x, P, sensors, params), repeat))
        if capacity is None:
            t["closed_form"].append(_median_ms(partial(decide_closed_form, prob), repeat))
        t["lp_highs"].append(_median_ms(partial(decide_lp_highs, prob), repeat))
        if milp:
            t0 = time.perf_counter()
            exact = decide_milp(prob, SolverOptions(time_limit=60.0))
            t["milp"].append(1e3 * (time.perf_counter() - t0))
            lp = decide_lp(prob)
            gap = (lp.objective - exact.objective) / abs(exact.objective)
            worse += int(gap > 1e-9)
            max_gap = max(max_gap, gap)
    row: dict[str, Any] = {
        "N": N,
        "M": M,
        "capacity": capacity,
        "candidates": M * N * 9,
        "problems": problems,
        "repeat": repeat,
    }
    for k, v in t.items():
        row[f"{k}_ms"] = float(np.median(v)) if v else None
    if milp:
        row["lp_post_worse"] = worse
        row["max_gap"] = max_gap
    return row


def run(
    sensors: Sequence[int] = SENSORS,
    targets: Sequence[int] = TARGETS,
    problems: int = 3,
    repeat: int = 7,
    milp: bool = True,
    progress: Callable[[str], None] | None = None,
) -> list[dict[str, Any]]:
    """Every (N, M) with capacity none and ``⌈1.5 M / N⌉``; rows in that order."""
    rows = []
    for N in sensors:
        for M in targets:
            for cap in (None, math.ceil(1.5 * M / N)):
                if progress is not None:
                    progress(f"N={N} M={M} capacity={cap if cap is not None else 'none'}")
                rows.append(bench_case(N, M, cap, problems, repeat, milp))
    return rows


def goals(rows: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The issue's two goals at the largest size (50 × 100)."""
    big = [r for r in rows if r["N"] == max(r2["N"] for r2 in rows)]
    big = [r for r in big if r["M"] == max(r2["M"] for r2 in big)]
    with_cap = next((r for r in big if r["capacity"] is not None), None)
    no_cap = next((r for r in big if r["capacity"] is None), None)
    out: dict[str, Any] = {}
    if with_cap is not None:
        out["decision_with_capacity_ms"] = with_cap["decision_ms"]
        out["decision_goal_ms"] = GOAL_DECISION_MS
        out["decision_goal_met"] = with_cap["decision_ms"] < GOAL_DECISION_MS
    if no_cap is not None:
        out["closed_form_ms"] = no_cap["closed_form_ms"]
        out["closed_form_goal_ms"] = GOAL_CLOSED_FORM_MS
        out["closed_form_goal_met"] = no_cap["closed_form_ms"] < GOAL_CLOSED_FORM_MS
        out["decision_no_capacity_ms"] = no_cap["decision_ms"]
    if big:
        out["size"] = f"{big[0]['N']}x{big[0]['M']}"
    return out
