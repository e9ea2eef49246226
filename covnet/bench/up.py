"""``covnet bench up``: a scenario (the paper's by default) over real processes in lockstep,
timed; with ``--sensors N,...`` networks of those sizes against a closed-loop zenoh probe of the
same message pattern, measured in the same run.

``--foxglove``: pairs of runs, without and with ``covnet up --foxglove`` (the live view served
by the recorder), alternated, and the ratio of their median scans per second.

Per run: scans per second over the manager's loop (READY to the last scan fused, every metric
episode), the whole wall time including process start-up, per-scan latency (command published
to scan fused) p50/p99, the manager's core time per scan (predict + allocate + fuse) and its
share of the loop: the rest is the bus and the other processes.

``--sensors``: for each size ``N`` the kind's bench network (``bench:up-config``; covariance
control: :func:`covnet.covariance_control.network_sizes.bench_config`, every sensor enabled at
every scan: one command out, ``N`` measurements back), its sensors hosted as ``covnet up``
hosts them (``--sensors-per-process``, default
:func:`covnet.processes.up.default_sensors_per_process`),
and, alternating with it, :mod:`covnet.bench.zenoh_probe` with the same ``N``, hosting, scan count
and message sizes, twice: its responders served by one loop per process as covnet's hosted
sensors are (``ratio = scans_per_s / probe_scans_per_s``), and with a thread per responder, as
covnet hosted them before (``ratio_threads``, against ``probe_threads_scans_per_s``).
"""

from __future__ import annotations

import contextlib
import io
import json
import resource
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import yaml

from covnet import kinds
from covnet.errors import UpError, UsageError
from covnet.processes.interrupts import EXIT_INTERRUPTED
from covnet.processes.launch import ProcessSpec, Supervisor
from covnet.processes.up import default_sensors_per_process, free_port, sensor_hosts, up
from covnet.runs.rundir import writing
from covnet.wire.messages import new_run_id

#: scans of each run of a sized network (and of its probe)
SIZED_SCANS = 200


def _covnet_row(
    kind: Any,
    sc: Any,
    config_path: str,
    out: Path,
    per_process: int | None,
    foxglove: str | None = None,
) -> dict[str, Any]:
    t0, cpu0 = time.perf_counter(), _children_cpu_s()
    sink = io.StringIO()
    try:
        with contextlib.redirect_stdout(sink):
            status = up(
                kind, sc, config_path, out, run_id=new_run_id(),
                sensors_per_process=per_process, foxglove=foxglove,
            )  # fmt: skip
    except UpError as exc:  # with what the processes said (it went to the sink)
        raise UpError(f"{exc}; the run's last output:\n{sink.getvalue()[-3000:]}") from None
    wall, cpu = time.perf_counter() - t0, _children_cpu_s() - cpu0
    if status == EXIT_INTERRUPTED:  # Ctrl-C or SIGTERM stopped the run: it stops the bench
        raise KeyboardInterrupt
    if status != 0:
        raise UpError(f"covnet up failed (status {status}):\n{sink.getvalue()[-3000:]}")
    net = json.loads((out / "network.json").read_text())
    return {
        "scans": net["scans"],
        "scans_per_s": net["scans_per_s"],
        "wall_s": wall,
        "scan_p50_ms": net["scan_latency"]["p50_ms"],
        "scan_p99_ms": net["scan_latency"]["p99_ms"],
        "core_p50_ms": net["core"]["p50_ms"],
        "core_share": net["core_share"],
        "measurement_p50_ms": net["measurement_latency"]["p50_ms"],
        "cpu_ms_per_scan": 1e3 * cpu / max(net["scans"], 1),
    }


def _children_cpu_s() -> float:
    """CPU seconds (user + system) of this process's children that have ended: a run's
    processes, all of them, from start-up to exit, when taken before and after it."""
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def run(
    kind: Any,
    sc: Any,
    config_path: str,
    tmp: Path,
    *,
    repeat: int = 3,
    quiet: bool = False,
    foxglove: bool = False,
) -> list[dict[str, Any]]:
    """``repeat`` lockstep runs of ``sc`` (a config of the scenario kind ``kind``), one row
    each (from the manager's ``network.json``).  ``foxglove``: ``repeat`` pairs instead, each a
    run without and a run with ``covnet up --foxglove`` (the live server on a free port of
    127.0.0.1, no client), alternated; each row says which (``foxglove``)."""
    rows = []
    modes = (False, True) if foxglove else (False,)
    for i in range(repeat):
        for live in modes:
            address = f"127.0.0.1:{free_port()}" if live else None
            out = tmp / f"run{i}{'-foxglove' if live else ''}"
            rows.append(_covnet_row(kind, sc, config_path, out, None, address))
            rows[-1]["foxglove"] = live
            if not quiet:
                what = " with --foxglove" if live else ""
                print(
                    f"run {i + 1}/{repeat}{what}: {rows[-1]['scans_per_s']:.0f} scans/s", flush=True
                )
    return rows


def probe(
    n_sensors: int,
    per_process: int,
    scans: int,
    *,
    command_bytes: int,
    measurement_bytes: int,
    threads: bool = False,
    taps: int = 0,
) -> dict[str, Any]:
    """One closed-loop probe run (:mod:`covnet.bench.zenoh_probe`): ``n_sensors`` responders,
    ``per_process`` to a process (``threads``: a thread each, else one loop per process);
    its ``RESULT``.  ``taps``: that many bare recording subscribers beside it (what a recorder
    of every message costs the probe at least); ``tap_messages`` then says how many messages
    each kept."""
    py = sys.executable
    run_id = new_run_id()
    listen = f"tcp/127.0.0.1:{free_port()}"
    specs = [
        ProcessSpec(
            "commander",
            [py, "-m", "covnet.bench.zenoh_probe", "commander", "--listen", listen, "--run", run_id,
             "--sensors", str(n_sensors), "--scans", str(scans),
             "--command-bytes", str(command_bytes), "--taps", str(taps)],
        ),
    ]  # fmt: skip
    for i in range(taps):
        specs.append(ProcessSpec(
            f"tap-{i}",
            [py, "-m", "covnet.bench.zenoh_probe", "tap", "--connect", listen, "--run", run_id,
             "--id", str(i)],
        ))  # fmt: skip
    ids = [str(i) for i in range(n_sensors)]
    for name, hosted in sensor_hosts(ids, per_process):
        argv = [
            py,
            "-m",
            "covnet.bench.zenoh_probe",
            "responders",
            "--connect",
            listen,
            "--run",
            run_id,
        ]
        argv += ["--measurement-bytes", str(measurement_bytes)] + ["--threads"] * threads
        for rid in hosted:
            argv += ["--id", rid]
        specs.append(ProcessSpec(f"responders-{name}", argv))
    cpu0 = _children_cpu_s()
    with Supervisor(specs, on_line=lambda name, line: None) as sup:
        rc = sup.wait("commander", timeout=600)
        lines = sup.output("commander")
        kept = []
        for i in range(taps):
            sup.wait(f"tap-{i}", timeout=30)
            said = [ln for ln in sup.output(f"tap-{i}") if ln.startswith("TAP ")]
            kept.append(int(said[-1].split()[1]) if said else None)
    cpu = _children_cpu_s() - cpu0
    result = next((ln for ln in lines if ln.startswith("RESULT ")), None)
    if rc != 0 or result is None:
        raise RuntimeError(f"the zenoh probe failed (status {rc}): {lines[-20:]}")
    out: dict[str, Any] = json.loads(result[len("RESULT ") :])
    out["cpu_ms_per_scan"] = 1e3 * cpu / max(scans, 1)
    if taps:
        out["tap_messages"] = kept
    return out


def run_sizes(
    kind: Any,
    sc: Any,
    sizes: Sequence[int],
    tmp: Path,
    *,
    repeat: int = 3,
    per_process: int | None = None,
    scans: int | None = None,
    quiet: bool = False,
) -> list[dict[str, Any]]:
    """Per size and repeat: covnet up of the kind's bench network of that size (``scans``
    scans, default :data:`SIZED_SCANS`), then the probe of the same pattern; one row each
    (module docstring)."""
    from covnet.bench.zenoh_probe import command_bytes, measurement_bytes  # bench only (start-up)

    scans = SIZED_SCANS if scans is None else scans

    make = kinds.command(kind, "bench:up-config", "a bench network of N sensors")
    networks = {}
    for n in sizes:  # every size's network before any run: a refusal costs no run
        try:
            networks[n] = make(sc, n, scans)
        except ValueError as exc:  # the config cannot make it (a radar in a scaled family)
            raise UsageError(f"--config, --sensors {n}: {exc}") from None
    rows = []
    for n in sizes:
        path = tmp / f"network-{n}.yaml"
        with writing(path):
            path.write_text(yaml.safe_dump(networks[n], sort_keys=False))
        kind_n, sc_n = kinds.load(path)
        k = per_process if per_process is not None else default_sensors_per_process(n)
        for i in range(repeat):
            row: dict[str, Any] = {
                "n_sensors": n,
                "sensors_per_process": k,
                "sensor_processes": -(-n // k),
                "run": i + 1,
            }
            row |= _covnet_row(kind_n, sc_n, str(path), tmp / f"run-{n}-{i}", k)
            pr, pt = (
                probe(
                    n,
                    k,
                    row["scans"],
                    command_bytes=command_bytes(n),
                    measurement_bytes=measurement_bytes(),
                    threads=threads,
                )  # fmt: skip
                for threads in (False, True)
            )
            row |= {
                "probe_scans_per_s": pr["scans_per_s"],
                "probe_p50_ms": pr["p50_ms"],
                "probe_p99_ms": pr["p99_ms"],
                "probe_cpu_ms_per_scan": pr["cpu_ms_per_scan"],
                "ratio": row["scans_per_s"] / pr["scans_per_s"],
                "probe_threads_scans_per_s": pt["scans_per_s"],
                "ratio_threads": row["scans_per_s"] / pt["scans_per_s"],
            }
            rows.append(row)
            if not quiet:
                print(
                    f"N = {n}, run {i + 1}/{repeat}: covnet {row['scans_per_s']:.0f} scans/s, "
                    f"probe {pr['scans_per_s']:.0f} scans/s (thread per responder: "
                    f"{pt['scans_per_s']:.0f})",
                    flush=True,
                )
    return rows
