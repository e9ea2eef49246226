"""``covnet bench up``: a scenario (the paper's by default) over real processes in lockstep,
timed.

Per run: scans per second over the manager's loop (READY to the last scan fused, every metric
episode), the whole wall time including process start-up, per-scan latency (command published
to scan fused) p50/p99, the manager's core time per scan (predict + allocate + fuse) and its
share of the loop: the rest is the bus and the other processes.
"""

from __future__ import annotations

import contextlib
import io
import json
import time
from pathlib import Path
from typing import Any

from covnet.messages import new_run_id
from covnet.up import up


def run(
    kind: Any, sc: Any, config_path: str, tmp: Path, *, repeat: int = 3, quiet: bool = False
) -> list[dict[str, Any]]:
    """``repeat`` lockstep runs of ``sc`` (a config of the scenario kind ``kind``), one row
    each (from the manager's ``network.json``)."""
    rows = []
    for i in range(repeat):
        out = tmp / f"run{i}"
        t0 = time.perf_counter()
        sink = io.StringIO()
        with contextlib.redirect_stdout(sink):
            status = up(kind, sc, config_path, out, run_id=new_run_id())
        wall = time.perf_counter() - t0
        if status != 0:
            raise RuntimeError(f"covnet up failed (status {status}):\n{sink.getvalue()[-2000:]}")
        net = json.loads((out / "network.json").read_text())
        rows.append(
            {
                "scans": net["scans"],
                "scans_per_s": net["scans_per_s"],
                "wall_s": wall,
                "scan_p50_ms": net["scan_latency"]["p50_ms"],
                "scan_p99_ms": net["scan_latency"]["p99_ms"],
                "core_p50_ms": net["core"]["p50_ms"],
                "core_share": net["core_share"],
                "measurement_p50_ms": net["measurement_latency"]["p50_ms"],
            }
        )
        if not quiet:
            print(f"run {i + 1}/{repeat}: {net['scans_per_s']:.0f} scans/s", flush=True)
    return rows
