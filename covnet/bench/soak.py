"""``covnet bench soak``: long network runs, watched for leaks (issue 14, "Soak").

Two phases, each one ``covnet up`` of the config (one metric: its first, or ``metric``) as a
child process in its own process group:

- **lockstep**: ``scans`` scans as fast as the machine goes (20 000 by default);
- **realtime**: ``--realtime --speed speed`` for ``realtime_s`` seconds of wall clock (the
  config's period divided by ``speed``: 600 s at speed 10 is 6 000 scans of the paper's 1 s).

Every ``interval_s`` the resident memory (``VmRSS`` of ``/proc/PID/status``) and the open file
descriptors (the entries of ``/proc/PID/fd``) of every process of the network are sampled: the
launcher, and every process ``processes.json`` names (re-read each time: it is rewritten on
restarts). The phase's time runs from the manager's ``READY`` to its last scan (its last
``[status]`` line, ``scan N/N``); samples before and after are start-up and wind-down, not
counted. Per process, after a warm-up of the first ``warmup`` (10 %) of that time, *growth* is
the median of the last tenth of the samples against the median of the first tenth, in per cent
(flat: under :data:`FLAT_PCT`).  The warm-up also covers the first
:data:`covnet.runs.columns.BLOCK` scans (:func:`phase_warmup`): the manager's result columns
open their spill files there, once, a step of one descriptor a column and not a leak (a
3 000-scan run took it at a third of its time).

Latency per window: the phase's scans in ``windows`` consecutive groups (by scan), p50 and p99
of each scan's latency, taken from the run's ``recording.mcap`` with the manager's own stamps:
from ``Command(k).t_sent_ns`` to ``Status(k).t_sent_ns``, i.e. the scan's latency (command
published to scan fused) plus the report (in real time, published at once; in lockstep, just
after ``Command(k+1)``, so the next scan's decision, usually done ahead, is in it too); and the
recorder's lag, its receipt of ``Command(k)`` minus ``t_sent_ns`` (the recorder stamps on
arrival; it is off the scan loop's critical path and may fall behind). ``network.json``'s
whole-run p50/p99 (command published to scan fused, every scan) are in the phase's summary row
for comparison. The raw samples go to ``soak_samples.json`` in the run directory.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import statistics
import subprocess
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from covnet.bench.child import Child
from covnet.errors import UpError, UsageError
from covnet.kinds import load
from covnet.runs.columns import BLOCK
from covnet.runs.recording import read_recording
from covnet.runs.rundir import writing
from covnet.wire import messages as msg

#: the lockstep phase's scans when ``--scans`` is not given
SOAK_SCANS = 20_000

__all__ = [
    "FLAT_PCT",
    "growth",
    "latency_windows",
    "main",
    "run",
    "sample_process",
    "scan_latencies",
]

FLAT_PCT = 5.0
"""A process is flat when its RSS and its open descriptors grow by less than this (per cent)."""


# --------------------------------------------------------------------------------------------
# sampling
# --------------------------------------------------------------------------------------------


def sample_process(pid: int) -> tuple[int, int] | None:
    """``(VmRSS in kB, open file descriptors)`` of process ``pid`` now, or None when it is gone
    (or a zombie: no ``VmRSS``)."""
    try:
        with open(f"/proc/{pid}/status") as f:
            rss = next((int(line.split()[1]) for line in f if line.startswith("VmRSS:")), None)
        fds = len(os.listdir(f"/proc/{pid}/fd"))
    except (OSError, ValueError):
        return None
    return None if rss is None else (rss, fds)


@dataclass
class _Series:
    """One process's samples: ``(t_s, rss_kb, fds)``, ``t_s`` from the phase's start."""

    pid: int
    samples: list[tuple[float, int, int]] = field(default_factory=list)


def phase_warmup(
    warmup: float,
    scans: int,
    lines: Sequence[tuple[float, str]] = (),
    t0: float = 0.0,
    t1: float = 1.0,
) -> float:
    """The share of a phase's time ``[t0, t1]`` left out before growth is measured: ``warmup``,
    and at least until the phase's scan ``BLOCK + 1``.  A :class:`covnet.runs.columns.Column`
    opens its spill file when its first block of :data:`~covnet.runs.columns.BLOCK` rows is
    full and keeps it to the end: a run of more scans steps up by one descriptor a column
    there, once.  When is that: the first of the run's ``lines`` (``(t, text)``, times on the
    same clock as ``t0``) that is a ``[status]`` line past scan ``BLOCK`` (such a line comes
    after the step: at most ``0.9``); without one, estimated from an even pace (plus 5 % for the
    start's slower scans, at most half the phase)."""
    if scans <= BLOCK:
        return warmup
    rx = re.compile(rf"\b(\d+)/{scans}\b")
    for t, text in lines:
        m = rx.search(text) if text.startswith("[status]") else None
        if m is not None and int(m.group(1)) > BLOCK and t1 > t0:
            return max(warmup, min(0.9, (t - t0) / (t1 - t0)))
    return max(warmup, min(0.5, (BLOCK + 1) / scans + 0.05))


def growth(
    samples: Sequence[tuple[float, int, int]], t0: float, t1: float, warmup: float = 0.1
) -> dict[str, Any]:
    """The growth of one process over ``[t0, t1]`` after a warm-up of the first ``warmup`` of
    it (module docstring): ``samples`` (after the warm-up), ``rss_start_kb`` / ``rss_end_kb``
    (medians of the first and last tenth, at least one sample each), ``rss_max_kb``,
    ``rss_growth_pct``, and the same for descriptors (``fd_*``); the values are None without
    samples."""
    t_warm = t0 + warmup * (t1 - t0)
    kept = [s for s in samples if t_warm <= s[0] <= t1]
    out: dict[str, Any] = {"samples": len(kept)}
    if len(kept) < 2:  # the same keys, None: not measured (one sample shows no growth: it
        # was its own start and end, "+0.0 %, flat")
        for what, unit in (("rss", "_kb"), ("fd", "")):
            out.update({f"{what}_{k}{unit}": None for k in ("start", "end", "max")})
            out[f"{what}_growth_pct"] = None
        return out
    n = max(1, len(kept) // 10)
    for what, i, unit in (("rss", 1, "_kb"), ("fd", 2, "")):
        start = statistics.median(s[i] for s in kept[:n])
        end = statistics.median(s[i] for s in kept[-n:])
        out[f"{what}_start{unit}"] = start
        out[f"{what}_end{unit}"] = end
        out[f"{what}_max{unit}"] = max(s[i] for s in kept)
        out[f"{what}_growth_pct"] = 100.0 * (end - start) / start if start else 0.0
    return out


# --------------------------------------------------------------------------------------------
# latency from the recording
# --------------------------------------------------------------------------------------------


def scan_latencies(recording: Path) -> list[tuple[int, int, int, int, int]]:
    """``(episode, scan, t_sent_ns, latency_ns, recorder_lag_ns)`` of every scan whose command
    and status are in the recording, in scan order: the command's ``t_sent_ns``,
    ``Status(k).t_sent_ns`` minus it, and the recorder's receipt of the command minus it
    (module docstring). Payloads that do not decode are skipped."""
    sent: dict[tuple[int, int], tuple[int, int]] = {}
    done: dict[tuple[int, int], int] = {}
    for s in read_recording(recording):
        parts = s.key.split("/")
        if len(parts) == 4 and parts[2] == "cmd":
            try:
                cmd = msg.decode_command(s.key, s.payload)
            except msg.WireError:
                continue
            sent.setdefault((cmd.episode, cmd.scan), (cmd.t_sent_ns, s.t_recv_ns))
        elif len(parts) == 4 and parts[2:] == ["manager", "status"]:
            try:
                st = msg.decode_as(s.payload, msg.Status)
            except msg.WireError:
                continue
            done.setdefault((st.episode, st.scan), st.t_sent_ns)
    return [
        (e, k, t, done[(e, k)] - t, t_rec - t)
        for (e, k), (t, t_rec) in sorted(sent.items())
        if (e, k) in done
    ]


def latency_windows(
    lat: Sequence[tuple[int, int, int, int, int]],
    windows: int,
    load: Sequence[tuple[float, float]] = (),
) -> list[dict[str, Any]]:
    """``lat`` (:func:`scan_latencies`) cut into ``windows`` consecutive groups of scans: per
    group its first and last scan, its size, the latency's p50 / p99 / max and the recorder
    lag's p50 / p99, in ms; with ``load`` (``(time.monotonic(), 1-minute load average)``
    samples) also the mean load average while the group ran (None without a sample in it)."""
    out: list[dict[str, Any]] = []
    if not lat:
        return out
    for i, part in enumerate(np.array_split(np.arange(len(lat)), max(1, windows))):
        if part.size == 0:
            continue
        ms = np.array([lat[j][3] for j in part], dtype=np.float64) / 1e6
        lag = np.array([lat[j][4] for j in part], dtype=np.float64) / 1e6
        t_lo, t_hi = lat[int(part[0])][2] / 1e9, lat[int(part[-1])][2] / 1e9
        loads = [v for t, v in load if t_lo <= t <= t_hi]
        out.append(
            {
                "window": i + 1,
                "first_scan": lat[int(part[0])][1],
                "last_scan": lat[int(part[-1])][1],
                "scans": int(part.size),
                "p50_ms": float(np.percentile(ms, 50)),
                "p99_ms": float(np.percentile(ms, 99)),
                "max_ms": float(ms.max()),
                "recorder_lag_p50_ms": float(np.percentile(lag, 50)),
                "recorder_lag_p99_ms": float(np.percentile(lag, 99)),
                "load_1min": round(statistics.fmean(loads), 2) if loads else None,
            }
        )
    return out


def _load_average() -> float | None:
    """The machine's 1-minute load average (``/proc/loadavg``), or None."""
    try:
        with open("/proc/loadavg") as f:
            return float(f.read().split()[0])
    except (OSError, ValueError, IndexError):
        return None


# --------------------------------------------------------------------------------------------
# one phase
# --------------------------------------------------------------------------------------------


def _soak_config(config_path: str, work: Path, scans: int, metric: str | None) -> Path:
    """The config with ``scans`` scans and one metric, written to ``work`` (relative security
    paths made absolute, since the file moves)."""
    kind, cfg = load(config_path)
    data = yaml.safe_load(Path(config_path).read_text())
    data["scans"] = int(scans)
    # the config's metrics as loaded (its own list or the default one: a config without
    # allocation.metrics ran all three, whatever --metric said, and timed the first only)
    metrics = getattr(getattr(cfg, "allocation", None), "metrics", None)
    if metrics:
        if metric is not None and metric not in _metric_names():
            raise UsageError(f"--metric: unknown metric {metric!r}")
        data.setdefault("allocation", {})["metrics"] = [metric or metrics[0]]
    elif metric is not None:
        raise UsageError(f"--metric: a {kind.title} scenario has no allocation metrics")
    sec = (data.get("network") or {}).get("security") or {}
    base = Path(config_path).resolve().parent
    for k in ("credentials_file",):
        if sec.get(k):
            sec[k] = str(base / sec[k])
    if isinstance(sec.get("tls"), dict):
        for k in ("ca", "cert_dir"):
            if sec["tls"].get(k):
                sec["tls"][k] = str(base / sec["tls"][k])
    path = work / f"soak-{scans}.yaml"
    with writing(path):
        path.write_text(yaml.safe_dump(data, sort_keys=False))
    load(str(path))  # the same checks as covnet up makes, before anything starts
    return path


def _metric_names() -> list[str]:
    """The metric registry's names (start-up: imported for a soak with --metric only)."""
    from covnet.core.metrics import METRICS

    return list(METRICS)


def _phase(
    name: str,
    cfg: Path,
    out: Path,
    scans: int,
    *,
    realtime: bool,
    speed: float,
    interval_s: float,
    warmup: float,
    windows: int,
    timeout_s: float,
    quiet: bool,
) -> list[dict[str, Any]]:
    """One soak phase (module docstring): its rows, per process and per latency window, then
    the phase's summary row."""
    argv = ["up", str(cfg), "--out", str(out), "--no-figures", "--run", msg.new_run_id()]
    if realtime:
        argv += ["--realtime", "--speed", f"{speed:g}"]
    series: dict[str, _Series] = {}
    load: list[tuple[float, float]] = []
    child = Child(argv)
    t_start = time.monotonic()
    try:
        while child.proc.poll() is None:
            now = time.monotonic()
            if now - t_start > timeout_s:
                raise UpError(f"{name}: covnet up still running after {timeout_s:.0f} s")
            la = _load_average()
            if la is not None:
                load.append((now, la))
            pids = {"launcher": child.proc.pid}
            try:
                pids.update(json.loads((out / "processes.json").read_text()))
            except (OSError, ValueError):
                pass  # not written yet, or being rewritten
            for proc_name, pid in pids.items():
                if not isinstance(pid, int):  # "hosts": which process hosts each sensor
                    continue
                got = sample_process(int(pid))
                if got is None:
                    continue
                s = series.get(proc_name)
                if s is None or s.pid != pid:  # a restarted process is a new series
                    s = series[proc_name] = _Series(int(pid))
                s.samples.append((now - t_start, *got))
            try:
                child.proc.wait(timeout=interval_s)
            except subprocess.TimeoutExpired:
                pass
    finally:
        child.stop()
    if child.proc.returncode != 0:
        tail = "\n".join(text for _, text in child.lines[-30:])
        raise UpError(f"{name}: covnet up exited {child.proc.returncode}:\n{tail}")
    t_ready = child.first(r"^\[manager\] READY")
    t_end = child.first(rf"^\[status\] .*\b{scans}/{scans}\b") or child.first(r"\[manager\] DONE")
    if t_ready is None or t_end is None:
        raise UpError(f"{name}: no READY or last scan in the output")
    t0, t1 = t_ready - t_start, t_end - t_start
    lines = [(t - t_start, text) for t, text in list(child.lines)]
    warm = phase_warmup(warmup, scans, lines, t0, t1)
    raw = {n: {"pid": v.pid, "t_s,rss_kb,fds": v.samples} for n, v in series.items()}
    loads = [(t - t_start, v) for t, v in load]
    doc = {"t0_s": t0, "t1_s": t1, "load_1min": loads, "processes": raw}
    with writing(out / "soak_samples.json"):
        (out / "soak_samples.json").write_text(json.dumps(doc))
    rows: list[dict[str, Any]] = []
    for proc_name in sorted(series, key=lambda n: (n != "launcher", n != "manager", n)):
        s = series[proc_name]
        g = growth(s.samples, t0, t1, warm)
        # None: no sample after the warm-up (a phase shorter than a few intervals)
        pct = (g["rss_growth_pct"], g["fd_growth_pct"])
        flat = all(p < FLAT_PCT for p in pct) if g["rss_growth_pct"] is not None else None
        row = {"phase": name, "row": "process", "process": proc_name, "pid": s.pid}
        rows.append({**row, **g, "flat": flat})
    lat = scan_latencies(out / "recording.mcap")
    rows += [{"phase": name, "row": "latency", **w} for w in latency_windows(lat, windows, load)]
    net = json.loads((out / "network.json").read_text())
    rows.append(
        {
            "phase": name,
            "row": "summary",
            "scans": net["scans"],
            "loop_s": round(t1 - t0, 1),
            "scans_per_s": net["scans_per_s"],
            "scan_p50_ms": net["scan_latency"]["p50_ms"],
            "scan_p99_ms": net["scan_latency"]["p99_ms"],
            "late": net["late"],
            "lost": net["lost"],
            "interval_s": interval_s,
            "warmup": warm,
        }
    )
    if not quiet:
        print(f"{name}: {net['scans']} scans in {t1 - t0:.0f} s", flush=True)
    return rows


def run(
    config_path: str,
    scans: int = 20_000,
    realtime_s: float = 600.0,
    *,
    speed: float = 10.0,
    metric: str | None = None,
    interval_s: float = 2.0,
    warmup: float = 0.1,
    windows: int = 10,
    work: Path | None = None,
    quiet: bool = False,
) -> list[dict[str, Any]]:
    """The soak (module docstring): a lockstep phase of ``scans`` scans (none when 0), then a
    real-time phase of ``realtime_s`` seconds at ``speed`` (none when 0); returns every row
    (``row``: ``process`` per process, ``latency`` per window, ``summary`` per phase). The
    run directories go to ``work`` (a temporary directory, removed, when None). Raises
    ``RuntimeError`` when a run fails; every process it started is stopped either way."""
    if scans < 0 or realtime_s < 0 or interval_s <= 0 or speed <= 0 or not 0 <= warmup < 1:
        raise ValueError("scans and realtime_s >= 0, interval_s and speed > 0, 0 <= warmup < 1")
    if work is None:
        with tempfile.TemporaryDirectory(prefix="covnet-soak-") as tmp:
            return run(
                config_path, scans, realtime_s, speed=speed, metric=metric,
                interval_s=interval_s, warmup=warmup, windows=windows, work=Path(tmp),
                quiet=quiet,
            )  # fmt: skip
    work.mkdir(parents=True, exist_ok=True)
    rows: list[dict[str, Any]] = []
    common: dict[str, Any] = {
        "speed": speed,
        "interval_s": interval_s,
        "warmup": warmup,
        "windows": windows,
        "quiet": quiet,
    }
    if scans:
        cfg = _soak_config(config_path, work, scans, metric)
        timeout = max(600.0, scans / 20)
        rows += _phase(
            "lockstep", cfg, work / "lockstep", scans, realtime=False, timeout_s=timeout, **common
        )
    if realtime_s:
        _, sc = load(config_path)
        period: Any = getattr(sc, "period_s", None) or getattr(sc, "scan_period_s", None) or 1.0
        rt_scans = max(1, round(realtime_s * speed / float(period)))
        cfg = _soak_config(config_path, work, rt_scans, metric)
        timeout = realtime_s + 300.0
        rows += _phase(
            "realtime", cfg, work / "realtime", rt_scans, realtime=True, timeout_s=timeout, **common
        )
    return rows


# --------------------------------------------------------------------------------------------
# the command
# --------------------------------------------------------------------------------------------


def _flat_word(flat: bool | None) -> str:
    return "-" if flat is None else "yes" if flat else "NO"


def _print_table(rows: list[dict[str, Any]]) -> None:
    def num(v: Any, fmt: str) -> str:  # "-": not measured, as wide as the number would be
        width = re.match(r"\+?(\d*)", fmt)
        return "-".rjust(int(width.group(1) or 0) if width else 0) if v is None else format(v, fmt)

    for phase in dict.fromkeys(r["phase"] for r in rows):
        summ = next(r for r in rows if r["phase"] == phase and r["row"] == "summary")
        print(
            f"{phase}: {summ['scans']} scans in {summ['loop_s']} s "
            f"({num(summ['scans_per_s'], '.0f')} scans/s), scan latency p50 "
            f"{num(summ['scan_p50_ms'], '.2f')} ms p99 {num(summ['scan_p99_ms'], '.2f')} ms, "
            f"late {summ['late']}, lost {summ['lost']}"
        )
        print(
            f"  {'process':>9} {'samples':>7} {'RSS start MB':>12} {'end MB':>7} {'max MB':>7} "
            f"{'growth':>7} {'fds':>9} {'growth':>7} {'flat':>5}"
        )
        procs = [r for r in rows if r["phase"] == phase and r["row"] == "process"]
        for r in procs:
            kb = ("rss_start_kb", "rss_end_kb", "rss_max_kb")
            mb = {k: None if r[k] is None else r[k] / 1024 for k in kb}
            fds = "-" if r["fd_start"] is None else f"{r['fd_start']:g}->{r['fd_end']:g}"
            print(
                f"  {r['process']:>9} {r['samples']:>7} {num(mb['rss_start_kb'], '12.1f')} "
                f"{num(mb['rss_end_kb'], '7.1f')} {num(mb['rss_max_kb'], '7.1f')} "
                f"{num(r['rss_growth_pct'], '+6.1f')}% {fds:>9} "
                f"{num(r['fd_growth_pct'], '+6.1f')}% {_flat_word(r['flat']):>5}"
            )
        if any(r["flat"] is None for r in procs):
            print(
                f"  (-: not measured, no sample after the warm-up: the phase's {summ['loop_s']} s "
                "of scans are too short for the sampling interval; give more --scans or "
                "--realtime-s, or a shorter --interval)"
            )
        print(
            f"  {'window':>9} {'scans':>11} {'p50 ms':>8} {'p99 ms':>8} {'max ms':>8} "
            f"{'recorder lag p50/p99 ms':>24} {'load':>5}"
        )
        for r in rows:
            if r["phase"] == phase and r["row"] == "latency":
                span = f"{r['first_scan']}-{r['last_scan']}"
                ms = f"{r['p50_ms']:>8.2f} {r['p99_ms']:>8.2f} {r['max_ms']:>8.2f}"
                lag = f"{r['recorder_lag_p50_ms']:.2f} / {r['recorder_lag_p99_ms']:.2f}"
                print(f"  {r['window']:>9} {span:>11} {ms} {lag:>24} {num(r['load_1min'], '5.2f')}")


#: the most latency windows a run is cut into (``--windows``)
MAX_WINDOWS = 10_000


def main(args: argparse.Namespace) -> int:
    """``covnet bench soak`` (its options: ``covnet.cli.app``; ``config``, ``metric`` (a list or
    None), ``json``, ``scans``, ``realtime_s``, ``speed``, ``interval``, ``windows``,
    ``work``): one JSON row per line with ``--json``, else a table per phase; exit 0 when
    every process is flat, 1 otherwise (a process not measured, in a phase too short for the
    sampling interval, is not shown flat)."""
    if args.scans is None:
        args.scans = SOAK_SCANS
    for name, low in (("scans", 0), ("realtime_s", 0), ("windows", 1)):
        value = getattr(args, name)
        flag = "--" + name.replace("_", "-")
        if not value >= low:  # nan too
            raise UsageError(f"{flag}: must be >= {low}, got {value}")
        if not math.isfinite(value):  # inf failed converting seconds to scans
            raise UsageError(f"{flag}: must be a finite number, got {value}")
    if args.windows > MAX_WINDOWS:  # each window's table is made up front
        raise UsageError(f"--windows: at most {MAX_WINDOWS}, got {args.windows}")
    for name in ("speed", "interval"):
        if not (math.isfinite(getattr(args, name)) and getattr(args, name) > 0):
            raise UsageError(f"--{name}: must be a finite number > 0, got {getattr(args, name)}")
    if args.scans == 0 and args.realtime_s == 0:
        raise UsageError("--scans and --realtime-s are both 0: nothing to run")
    if args.work:  # checked now: its runs' --out would refuse it only after the set-up (exit 1)
        work = Path(args.work)
        if work.exists() and not work.is_dir():
            raise UsageError(f"--work {args.work}: exists and is not a directory")
        if work.is_dir() and any(work.iterdir()):
            raise UsageError(
                f"--work {args.work}: not empty (an earlier soak's runs?); give a new or empty "
                "directory"
            )
    metrics = getattr(args, "metric", None) or []
    if len(metrics) > 1:  # (the first ran, silently)
        raise UsageError(f"--metric: a soak runs one metric, got {len(metrics)}")
    metric = metrics[0] if metrics else None
    rows = run(
        args.config,
        args.scans,
        args.realtime_s,
        speed=args.speed,
        metric=metric,
        interval_s=args.interval,
        windows=args.windows,
        work=Path(args.work) if args.work else None,
        quiet=bool(args.json),
    )
    if args.json:
        for row in rows:
            print(json.dumps(row))
    else:
        _print_table(rows)
    return 0 if all(r["flat"] for r in rows if r["row"] == "process") else 1
