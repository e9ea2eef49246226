"""Result hashes of the shipped configs, run through the CLI: the proof that a refactor changed
no result.  ``python tests/golden/golden.py OUT.json`` runs every case of :data:`CASES` with the
``covnet`` on ``sys.path`` and writes ``{case: {file: sha256}}``; ``tests/integration/
test_golden.py`` runs the same cases and compares them with ``tests/golden/hashes.json`` (made
on the code before the architecture change, issue 13; the four cases with covariance
intersection, ``run-paper-ci``, ``run-latency-ci``, ``compare`` and ``sweep``, recorded again
on December 5 after CI that gives one track all the weight returns that track's mean as it is:
the estimates moved by at most 1e-11 m, every decision and printed figure the same; the
three ``run-latency`` cases' ``summary.json`` recorded again the same day when its
``latency.unsolicited`` became ``network.json``'s (fused on time: 0 where it was 8, 8 and 6) and
``fallback_sent`` took the old count: the only two keys that changed, the arrays the same); the
``(issue 18)`` hashes of ``compare``, ``mc-mobile`` and ``mc-passive`` recorded again on December
6 when the intervals over seeds were cut to their quantity's range (``stats.seed_stats``'s
bounds): only ``*_ci_lo`` below 0 and ``*_ci_hi`` above 1 of a share changed (to 0 and 1), every
other key the same (each file compared key by key with the code before); ``compare``'s both
hashes again the same day when the grand mean NEES's interval ``nees_mean_ci_95`` was cut at 0
too (its lower end, -3.2 and -10.3 in that file, the only other change); and again on December
6 (a later session) when the messages it encodes to count ``bytes_per_scan`` got the fields real
ones have (a monotonic ``t_sent_ns``, a sensor's ``seq``): 1086.96 -> 1169.72, 1277.32 -> 1325.5
and 5336.52 -> 5500.68 bytes, the recording's counts, every other key the same.

A JSON file is hashed as its bytes; wall-clock keys (:data:`WALL_CLOCK_KEYS`) are removed first
and the rest re-serialised canonically only where a case says so (those files held timings
before issue 13 moved them to ``run.json``).  An ``.npz`` is hashed array by array (name, dtype,
shape, bytes), leaving out :data:`WALL_CLOCK_ARRAYS`.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
WALL_CLOCK_KEYS = frozenset(
    {
        "decision_time_s",
        "decision_time_median_s",
        "time_s",
        "wall_s",
        "median_time_s",
        "created_utc",
    }
)
MACHINE_KEYS = frozenset({"machine"})
"""Facts of the machine a batch ran on (the passive Monte Carlo's ``results.json`` keeps them
beside its timings: kernel version, processor): removed with the wall-clock keys, or the hash
would be of the host.  Issue 13's hashes of that file were re-taken this way on its code before
the architecture change (86fb5df) and on today's, which agree."""
WALL_CLOCK_ARRAYS = frozenset({"cost_s", "solve_s", "compare_s", "decision_s"})
_STATS = ("mean", "std", "ci_lo", "ci_hi")
ISSUE_18_KEYS = frozenset(
    {
        # the statistics over seeds issue 18 added to the batch tables (sweep, compare, mc),
        # after the fields that were there, which keep their values
        *(f"{n}_{s}" for n in ("rmse_position", "rmse_steady", "rmse_transient") for s in _STATS),
        *(f"{n}_{s}" for n in ("nees_steady", "allocation_rate") for s in _STATS),
        *(f"{n}_{s}" for n in ("p_trial", "exact_scan") for s in _STATS),
        "rmse_steady",
        "rmse_transient",
        "rmse_transient_max",
        "burn_in_scans",
        "point",
        "trial_hash",
        "ci_lo",
        "ci_hi",
        "n",
    }
)
"""Keys added by issue 18 (to :data:`BATCH_TABLES` only).  A table's hash under its old name is
taken with them removed (and the file re-serialised as its writer does): equal to the hash
recorded before issue 18, it proves every old field unchanged; the whole file's hash is under
``<file> (issue 18)``."""
LATER_KEYS = frozenset(
    f"{n}_{s}" for n in ("deadline_miss_rate", "late", "lost") for s in _STATS
)
"""Keys added to the sweep's table after both hashes were recorded (the spread over seeds of
the figure's last three panels, December 5): removed before either hash, their values checked
by ``tests/unit/test_latency.py`` against :func:`covnet.batches.stats.seed_stats`."""
BATCH_TABLES = frozenset({"sweep.json", "compare.json", "montecarlo.json", "results.json"})
"""The files issue 18 added keys to (the batch commands' tables)."""

SMALL_SWEEP = """
sweep:
  delay_ms: [0, 200]
  delay_kind: exponential
  loss: [0.0, 0.1]
  modes: [central, ci]
  account_for_loss: [false]
  late: [oosm]
  seeds: 1
"""


def _strip(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _strip(v) for k, v in obj.items() if k not in WALL_CLOCK_KEYS | MACHINE_KEYS}
    if isinstance(obj, list):
        return [_strip(v) for v in obj]
    return obj


def _drop(obj: Any, keys: frozenset[str]) -> Any:
    if isinstance(obj, dict):
        return {k: _drop(v, keys) for k, v in obj.items() if k not in keys}
    if isinstance(obj, list):
        return [_drop(v, keys) for v in obj]
    return obj


def hash_json(path: Path, strip: bool, drop: frozenset[str] = frozenset()) -> str:
    """The file's hash: its bytes; with ``strip`` the wall-clock keys removed and the rest
    canonical; with ``drop`` those keys removed first and the rest re-serialised as the
    batch writers write (``indent=2``, a newline)."""
    if not strip and not drop:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    data = json.loads(path.read_text())
    if drop:
        data = _drop(data, drop)
    if strip:
        data = _strip(data)
        return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()
    return hashlib.sha256((json.dumps(data, indent=2) + "\n").encode()).hexdigest()


def hash_npz(path: Path) -> str:
    h = hashlib.sha256()
    with np.load(path, allow_pickle=False) as z:
        for name in sorted(z.files):
            if name.split(".")[0] in WALL_CLOCK_ARRAYS:
                continue
            a = z[name]
            h.update(f"{name}|{a.dtype.str}|{a.shape}|".encode())
            h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


# case name -> (covnet argv with {out} and {cfg:<name>} placeholders, {file: strip?})
CASES: dict[str, tuple[list[str], dict[str, bool]]] = {
    "run-paper": (["run", "configs/paper.yaml"], {"summary.json": False, "arrays.npz": False}),
    "run-paper-info": (
        ["run", "configs/paper.yaml", "--fusion", "info"],
        {"summary.json": False, "arrays.npz": False},
    ),
    "run-paper-ci": (
        ["run", "configs/paper.yaml", "--fusion", "ci"],
        {"summary.json": False, "arrays.npz": False},
    ),
    "run-paper-peer": (
        ["run", "configs/paper.yaml", "--fusion", "peer"],
        {"summary.json": False, "arrays.npz": False},
    ),
    "run-latency": (["run", "configs/latency.yaml"], {"summary.json": False, "arrays.npz": False}),
    "run-latency-info": (
        ["run", "configs/latency.yaml", "--fusion", "info"],
        {"summary.json": False, "arrays.npz": False},
    ),
    "run-latency-ci": (
        ["run", "configs/latency.yaml", "--fusion", "ci"],
        {"summary.json": False, "arrays.npz": False},
    ),
    "run-mobile": (["run", "configs/mobile.yaml"], {"summary.json": True, "arrays.npz": False}),
    # recorded on December 6 with the code before the surveillance log's columns (6a8b7e2)
    "run-surveillance": (
        ["run", "configs/surveillance.yaml"],
        {"summary.json": False, "arrays.npz": False},
    ),
    "run-passive": (["run", "configs/passive.yaml"], {"association.json": True}),
    "mc-mobile": (["mc", "configs/mobile.yaml", "--trials", "3"], {"montecarlo.json": True}),
    "mc-passive": (["mc", "configs/passive.yaml", "--trials", "2"], {"results.json": True}),
    "compare": (
        ["compare", "configs/paper.yaml", "--runs", "2", "--modes", "central,ci,peer-info"],
        {"compare.json": False},
    ),
    "sweep": (["sweep", "{cfg:small_sweep}"], {"sweep.json": False}),
}
UP_CASES: dict[str, tuple[list[str], dict[str, bool]]] = {
    "up-paper": (["up", "configs/paper.yaml"], {"summary.json": False, "arrays.npz": False}),
    "up-mobile": (["up", "configs/mobile.yaml"], {"summary.json": True, "arrays.npz": False}),
    "up-passive": (["up", "configs/passive.yaml"], {"association.json": True}),
}


def _configs(work: Path) -> dict[str, str]:
    text = (ROOT / "configs/latency.yaml").read_text()
    text = text[: text.index("\nsweep:")] + "\n" + SMALL_SWEEP
    p = work / "small_sweep.yaml"
    p.write_text(text)
    return {"small_sweep": str(p)}


def run_case(name: str, argv: list[str], files: dict[str, bool], work: Path) -> dict[str, str]:
    out = work / name
    cfgs = _configs(work)
    args = [cfgs[a[5:-1]] if a.startswith("{cfg:") else a for a in argv]
    cmd = [sys.executable, "-m", "covnet", *args, "--out", str(out), "--no-figures"]
    if args[0] == "mc":
        cmd.remove("--no-figures")
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, env=os.environ.copy())
    if proc.returncode != 0:
        raise RuntimeError(f"{name}: {' '.join(cmd)} failed:\n{proc.stdout}\n{proc.stderr}")
    hashes = {}
    for f, strip in files.items():
        p = out / f
        if f.endswith(".npz"):
            hashes[f] = hash_npz(p)
            continue
        if f not in BATCH_TABLES:
            hashes[f] = hash_json(p, strip)
            continue
        hashes[f] = hash_json(p, strip, ISSUE_18_KEYS | LATER_KEYS)
        hashes[f"{f} (issue 18)"] = hash_json(p, strip, LATER_KEYS)
    return hashes


def run_all(work: Path, cases: dict[str, tuple[list[str], dict[str, bool]]]) -> dict[str, Any]:
    return {name: run_case(name, argv, files, work) for name, (argv, files) in cases.items()}


if __name__ == "__main__":
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        result = run_all(Path(tmp), {**CASES, **UP_CASES})
    Path(sys.argv[1]).write_text(json.dumps(result, indent=2, sort_keys=True) + "\n")
