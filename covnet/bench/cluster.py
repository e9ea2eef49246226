"""``covnet bench cluster``: the same sweep on the local process pool and on a local Dask
cluster (a real ``dask scheduler`` and two ``dask worker`` processes on 127.0.0.1, one thread
each: :class:`covnet.batches.cluster.LocalCluster`), in the same session, alternated (local, dask,
dask, local, ...) so that a drift of the machine's load falls on both; trials per second of
each, their ratio, and the per-task overhead of each backend (a batch of tasks that do
nothing: the wall time per task times the workers, i.e. what a task costs a worker besides
its own work).  Needs the ``covnet[cluster]`` extra.
"""

from __future__ import annotations

import json
import statistics
import time
from pathlib import Path
from typing import Any

from covnet.batches.trials import Batch, run_trials
from covnet.covariance_control import sweep as sw
from covnet.covariance_control.config import from_dict, load, normalised

WORKERS = 2
GRID = {
    "delay_ms": [0, 200, 350],
    "loss": [0.0, 0.1],
    "modes": ["central", "ci"],
    "account_for_loss": [False],
    "late": ["oosm"],
}
NOOP_TASKS = 400


def noop(task: Any) -> list[Any]:
    """A task that does nothing (the overhead measurement)."""
    return [None]


def _sweep_batch(config: Path, seeds: int) -> tuple[Batch, int]:
    data = normalised(load(config))
    data["sweep"] = {**(data.get("sweep") or {}), **GRID, "seeds": seeds}
    sc = from_dict(data, f"{config} (bench cluster)")
    b, points = sw.batch(sc, sc.allocation.metrics[0])
    return b, len(points) * seeds


def _timed(b: Batch, n: int, **where: Any) -> float:
    t0 = time.perf_counter()
    run_trials(b, n, **where)
    return time.perf_counter() - t0


def run(config: Path, seeds: int = 2, repeat: int = 4) -> dict[str, Any]:
    """The measurements (see the module docstring)."""
    from covnet.batches.cluster import LocalCluster  # dask: only this benchmark (start-up)

    b, trials = _sweep_batch(config, seeds)
    noop_batch = Batch("noop", noop, lambda p, s: None, [f"p{i}" for i in range(NOOP_TASKS)])
    rows: list[dict[str, Any]] = []
    with LocalCluster(workers=WORKERS, threads=1) as cluster:
        backends: dict[str, dict[str, Any]] = {
            "local": {"workers": WORKERS},
            "dask": {"cluster": cluster.address},
        }
        _timed(b, 1, **backends["dask"])  # the workers' first imports, outside the timing
        for r in range(repeat):
            order = ("local", "dask") if r % 2 == 0 else ("dask", "local")
            for name in order:
                wall = _timed(b, seeds, **backends[name])
                rows.append(
                    {"run": r + 1, "backend": name, "trials": trials, "wall_s": wall,
                     "trials_per_s": trials / wall}
                )  # fmt: skip
        overhead = {}
        for name in ("local", "dask"):
            walls = [_timed(noop_batch, 1, **backends[name]) for _ in range(2)]
            overhead[name] = min(walls) / NOOP_TASKS * WORKERS
    rate = {
        name: statistics.median(r["trials_per_s"] for r in rows if r["backend"] == name)
        for name in ("local", "dask")
    }
    return {
        "rows": rows,
        "trials_per_run": trials,
        "workers": WORKERS,
        "median_trials_per_s": rate,
        "ratio_dask_over_local": rate["dask"] / rate["local"],
        "trial_s_per_worker": WORKERS / rate["local"],
        "overhead_s_per_task": overhead,
        "noop_tasks": NOOP_TASKS,
    }


def main(args: Any) -> int:
    res = run(Path(args.config), repeat=args.repeat)
    if args.json:
        for r in res["rows"]:
            print(json.dumps(r))
        print(json.dumps({k: v for k, v in res.items() if k != "rows"}))
        return 0
    print(
        f"a {res['trials_per_run']}-trial sweep ({args.config}, 12 grid points x "
        f"{res['trials_per_run'] // 12} seeds), "
        f"{res['workers']} workers: the local pool against a local Dask cluster "
        "(scheduler + 2 workers, 1 thread each), alternated"
    )
    print(f"{'run':>4} {'backend':>8} {'wall s':>7} {'trials/s':>9}")
    for r in res["rows"]:
        print(f"{r['run']:>4} {r['backend']:>8} {r['wall_s']:>7.2f} {r['trials_per_s']:>9.2f}")
    rate = res["median_trials_per_s"]
    ov = res["overhead_s_per_task"]
    print(
        f"median: local {rate['local']:.2f} trials/s, dask {rate['dask']:.2f} trials/s: "
        f"dask/local = {res['ratio_dask_over_local']:.2f} (goal >= 0.8); a trial takes "
        f"{res['trial_s_per_worker']:.2f} s of a worker"
    )
    print(
        f"per-task overhead ({res['noop_tasks']} tasks that do nothing): local "
        f"{1e3 * ov['local']:.1f} ms, dask {1e3 * ov['dask']:.1f} ms of a worker"
    )
    return 0
