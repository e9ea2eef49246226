"""``covnet bench up --sensors N,... --steady``: the CPU a scan costs in the steady middle of a
long run, covnet's network against the zenoh probe of the same pattern (issue 29, "Bus").

``covnet bench up --sensors`` times whole 200-scan runs: their scans/s include the first
scans (before the gains and decisions repeat) and their CPU includes start-up and the end.
This measures what a scan costs once the network runs, per size and repeat, alternated:

- **covnet**: ``covnet up`` of the kind's bench network (``bench:up-config``, ``scans`` scans,
  lockstep, recorded, its sensors hosted as ``covnet up`` hosts them) as a child process; at
  every ``[status]`` line (one a second, ``scan k/N``) the CPU (``utime + stime`` of
  ``/proc/PID/stat``) of every process ``processes.json`` names; the CPU a scan is the
  difference between the first line past a third of the scans and the last line before the
  end, over the scans between them, in all and by role (manager, world, recorder, sensors);
- **probe**: :func:`covnet.bench.up.probe` (one loop a process, covnet's hosting) run for
  ``PROBE_SHORT`` and ``PROBE_SHORT + scans`` scans: the difference of their CPU over
  ``scans`` (start-up and end cancel).

Each row also says the cores each used (CPU a scan times scans/s) and the **budget**: the CPU a
scan covnet could spend and still run at one half of the probe's scans/s on the cores it uses
(``cores / (probe_scans_per_s / 2)``), and the cut of its CPU a scan that would take
(``1 - budget / cpu``; 0 when it is within it).
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import yaml

from covnet import kinds
from covnet.bench.child import Child
from covnet.bench.up import _children_cpu_s, probe
from covnet.errors import UpError, UsageError
from covnet.processes.up import default_sensors_per_process
from covnet.runs.rundir import writing

#: the steady runs' scans (covnet's and the probe's long run)
STEADY_SCANS = 3_000
#: the probe's short run, subtracted from its long one
PROBE_SHORT = 300

_STATUS = re.compile(r"\[status\] [^:]+: (\d+)/(\d+) ")
_TICK = os.sysconf("SC_CLK_TCK")


def _cpu_s(pid: int) -> float | None:
    """``utime + stime`` of process ``pid`` (all its threads), None when it is gone."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / _TICK


def _role(name: str) -> str:
    """``manager``, ``world``, ``recorder`` or ``sensors`` (a sensor's or a host's process)."""
    return name if name in ("manager", "world", "recorder") else "sensors"


class _Watched:
    """``covnet up ...`` as a :class:`~covnet.bench.child.Child`; at each ``[status]`` line, the
    scan it names and every process's CPU (:func:`_cpu_s`) once ``processes.json`` is there."""

    def __init__(self, args: list[str], out: Path) -> None:
        self.out = out
        self.samples: list[tuple[int, dict[str, float]]] = []
        self._pids: dict[str, int] | None = None
        self.child = Child(["up", *args], on_line=self._sample)

    def _processes(self) -> dict[str, int] | None:
        if self._pids is None:
            try:
                named = json.loads((self.out / "processes.json").read_text())
            except (OSError, ValueError):
                return None
            self._pids = {n: p for n, p in named.items() if isinstance(p, int)}
        return self._pids

    def _sample(self, line: str) -> None:
        m = _STATUS.search(line)
        pids = self._processes() if m else None
        if m and pids:
            by: dict[str, float] = {}
            for name, pid in pids.items():
                cpu = _cpu_s(pid)
                if cpu is not None:
                    by[_role(name)] = by.get(_role(name), 0.0) + cpu
            self.samples.append((int(m.group(1)), by))

    def wait(self, timeout: float) -> int:
        """Its exit status; it is stopped by PID whatever happens."""
        try:
            return self.child.proc.wait(timeout=timeout)
        finally:
            self.child.stop()


def steady_window(
    samples: Sequence[tuple[int, dict[str, float]]], scans: int
) -> tuple[int, dict[str, float]]:
    """The scans between the first sample past a third of ``scans`` and the last one before the
    last scan, and the CPU seconds each role used over them; ``UpError`` when fewer than two
    samples fall there (a run too short for its status lines)."""
    inside = [(k, by) for k, by in samples if scans / 3 <= k < scans]
    if len(inside) < 2 or inside[-1][0] <= inside[0][0]:
        raise UpError(
            f"too few progress lines in the middle of a {scans}-scan run to measure its steady "
            "state (one a second): give it more scans (--scans)"
        )
    (k0, a), (k1, b) = inside[0], inside[-1]
    return k1 - k0, {r: b[r] - a.get(r, 0.0) for r in b}


def _covnet(cfg: Path, out: Path, per_process: int, scans: int) -> dict[str, Any]:
    w = _Watched(
        [str(cfg), "--out", str(out), "--no-figures", "--sensors-per-process", str(per_process)],
        out,
    )
    rc = w.wait(timeout=max(600.0, scans / 5.0))
    if rc != 0:
        said = "\n".join(text for _, text in w.child.lines[-30:])
        raise UpError(f"covnet up failed (status {rc}):\n{said}")
    n, by = steady_window(w.samples, scans)
    net = json.loads((out / "network.json").read_text())
    cpu_ms = {r: 1e3 * s / n for r, s in sorted(by.items())}
    return {
        "scans_per_s": net["scans_per_s"],
        "cpu_ms_per_scan": sum(cpu_ms.values()),
        "cpu_ms_by_role": cpu_ms,
        "window_scans": n,
    }


def _probe(n: int, per_process: int, scans: int) -> dict[str, Any]:
    from covnet.bench.zenoh_probe import command_bytes, measurement_bytes  # bench only (start-up)

    cmd_b, meas_b = command_bytes(n), measurement_bytes()
    c0 = _children_cpu_s()
    probe(n, per_process, PROBE_SHORT, command_bytes=cmd_b, measurement_bytes=meas_b)
    c1 = _children_cpu_s()
    long = probe(n, per_process, PROBE_SHORT + scans, command_bytes=cmd_b, measurement_bytes=meas_b)
    c2 = _children_cpu_s()
    return {
        "scans_per_s": long["scans_per_s"],
        "cpu_ms_per_scan": 1e3 * ((c2 - c1) - (c1 - c0)) / scans,
    }


def budget_row(covnet: dict[str, Any], probe_: dict[str, Any]) -> dict[str, Any]:
    """The cores each used and covnet's budget for one half of the probe (module docstring)."""
    cores = covnet["cpu_ms_per_scan"] * covnet["scans_per_s"] / 1e3
    budget = 1e3 * cores / (probe_["scans_per_s"] / 2)
    return {
        "cores": cores,
        "probe_cores": probe_["cpu_ms_per_scan"] * probe_["scans_per_s"] / 1e3,
        "ratio": covnet["scans_per_s"] / probe_["scans_per_s"],
        "budget_ms_per_scan": budget,
        "cut_needed": max(0.0, 1.0 - budget / covnet["cpu_ms_per_scan"]),
    }


def run_steady(
    kind: Any,
    sc: Any,
    sizes: Sequence[int],
    tmp: Path,
    *,
    repeat: int = 2,
    per_process: int | None = None,
    scans: int | None = None,
    quiet: bool = False,
) -> list[dict[str, Any]]:
    """Per size and repeat, covnet's steady run then the probe's pair (module docstring); one
    row each."""
    scans = STEADY_SCANS if scans is None else scans
    if scans < 30:
        raise UsageError(f"--scans: a steady run needs at least 30 scans, got {scans}")
    make = kinds.command(kind, "bench:up-config", "a bench network of N sensors")
    rows = []
    for n in sizes:
        try:
            network = make(sc, n, scans)
        except ValueError as exc:
            raise UsageError(f"--config, --sensors {n}: {exc}") from None
        cfg = tmp / f"steady-{n}.yaml"
        with writing(cfg):
            cfg.write_text(yaml.safe_dump(network, sort_keys=False))
        k = per_process if per_process is not None else default_sensors_per_process(n)
        for i in range(repeat):
            c = _covnet(cfg, tmp / f"steady-{n}-{i}", k, scans)
            p = _probe(n, k, scans)
            row: dict[str, Any] = {"n_sensors": n, "sensors_per_process": k, "run": i + 1}
            row |= {"scans": scans, **c}
            row |= {
                "probe_scans_per_s": p["scans_per_s"],
                "probe_cpu_ms_per_scan": p["cpu_ms_per_scan"],
            }
            row |= budget_row(c, p)
            rows.append(row)
            if not quiet:
                print(
                    f"N = {n}, run {i + 1}/{repeat}: covnet {c['cpu_ms_per_scan']:.2f} ms of CPU "
                    f"a scan at {c['scans_per_s']:.0f} scans/s; probe {p['cpu_ms_per_scan']:.2f} "
                    f"ms at {p['scans_per_s']:.0f}",
                    flush=True,
                )
    return rows
