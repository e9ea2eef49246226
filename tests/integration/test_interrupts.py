"""Ctrl-C (SIGINT to the process group, as a terminal sends it, or to the command alone) and
SIGTERM at random moments, for every long command: the command exits 130 within seconds, prints
no traceback, leaves no process behind (every descendant it ever had is gone), and leaves a
valid directory: ``run.json`` says how it ended, and an interrupted network run replays.

The moments are seeded (``random.Random``): a failure names its seed and delay, and the same
test run repeats it.  Two interruptions per command here; ``-m slow`` runs ten."""

from __future__ import annotations

import json
import os
import random
import signal
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from multiproc import REPO, CovnetProcess

from covnet.runs.rundir import STATUSES

pytestmark = [pytest.mark.integration]

PAPER = str(REPO / "configs" / "paper.yaml")
HOW = ("group-sigint", "sigint", "sigterm")

# command -> (argv before --out, a line that says the work has begun, the delay range after it)
COMMANDS = {
    "run": (["run", PAPER], "scans in", (0.0, 1.5)),
    "sweep": (["sweep", PAPER], "sweeping", (0.3, 3.0)),
    "compare": (["compare", PAPER], "comparing", (0.3, 3.0)),
    "mc-mobile": (["mc", str(REPO / "configs" / "mobile.yaml")], "seeds x", (0.3, 3.0)),
    "mc-passive": (["mc", str(REPO / "configs" / "passive.yaml")], "monte carlo:", (0.3, 3.0)),
    "up": (["up", PAPER, "--realtime", "--speed", "10"], "[status]", (0.2, 2.0)),
}


def _procs() -> dict[int, tuple[int, str]]:
    out = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                fields = Path(f"/proc/{d}/stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            out[int(d)] = (int(fields[1]), fields[0])  # ppid, state
    return out


class Descendants:
    """Every process that was ever a descendant of ``root`` (polled every 20 ms)."""

    def __init__(self, root: int) -> None:
        self.root, self.seen = root, set[int]()
        self.parent: dict[int, int] = {}  # pid -> its parent when first seen
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._poll, daemon=True)
        self._thread.start()

    def _poll(self) -> None:
        while not self._stop.is_set():
            ps = _procs()
            front = {self.root}
            while front:
                kids = {p for p, (pp, _) in ps.items() if pp in front} - self.seen
                self.seen |= kids
                self.parent.update((k, ps[k][0]) for k in kids)
                front = kids
            self._stop.wait(0.02)

    def alive(self) -> list[int]:
        self._stop.set()
        self._thread.join()
        ps = _procs()
        return sorted(p for p in self.seen if p in ps and ps[p][1] != "Z")

    @staticmethod
    def describe(pids: list[int]) -> list[str]:
        out = []
        for pid in pids:
            try:
                out.append(f"{pid}: {Path(f'/proc/{pid}/stat').read_text()[:80]}")
            except OSError:
                out.append(f"{pid}: gone")
        return out


def _stop(p: CovnetProcess, how: str) -> tuple[int, float]:
    """Interrupt ``p`` the way ``how`` says; its exit status and the seconds it took."""
    t0 = time.monotonic()
    if p.proc.poll() is None:
        if how == "group-sigint":
            os.killpg(p.proc.pid, signal.SIGINT)
        else:
            p.proc.send_signal(signal.SIGINT if how == "sigint" else signal.SIGTERM)
    rc = p.wait(timeout=20)
    return rc, time.monotonic() - t0


def _stop_when(p: CovnetProcess, ready: Callable[[], bool], how: str) -> tuple[int, float]:
    """:func:`_stop` once ``ready()`` (polled every 20 ms, at most 60 s, while ``p`` runs)."""
    deadline = time.monotonic() + 60
    while not ready():
        assert p.proc.poll() is None and time.monotonic() < deadline, p.output()
        time.sleep(0.02)
    return _stop(p, how)


def _interrupt(tmp_path: Path, name: str, seed: int) -> None:
    argv, marker, (lo, hi) = COMMANDS[name]
    rng = random.Random(f"{name}-{seed}")
    how, delay = rng.choice(HOW), rng.uniform(lo, hi)
    where = f"{name}, seed {seed}: {how} {delay:.2f} s after {marker!r}"
    out = tmp_path / f"{name}-{seed}"
    p = CovnetProcess([*argv, "--out", str(out)])
    tree = Descendants(p.proc.pid)
    try:
        assert p.wait_for(marker, timeout=60) is not None, f"{where}: never began\n{p.output()}"
        time.sleep(delay)  # the random moment itself (the condition was waited for above)
        rc, took = _stop(p, how)
    finally:
        p.stop()
    left = tree.alive()
    text = p.output()
    assert rc in (130, 0), f"{where}: exit {rc}\n{text}"
    assert took < 10.0, f"{where}: took {took:.1f} s to stop"
    assert "Traceback" not in text, f"{where}: a traceback\n{text}"
    assert not left, f"{where}: processes left: {left}"
    info_path = out / "run.json"
    if info_path.is_file():
        info = json.loads(info_path.read_text())
        assert info.get("status") in STATUSES, f"{where}: run.json {info}"
        if rc == 0:
            assert info["status"] == "completed"
    if name == "up" and (out / "summary.json").is_file():
        rp = CovnetProcess(["replay", str(out)])
        try:
            assert rp.wait(timeout=120) == 0, f"{where}: replay\n{rp.output()}"
        finally:
            rp.stop()
        assert "identical" in rp.output()


@pytest.mark.timeout(300)
@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_interrupted_at_random_moments(tmp_path, name):
    for seed in range(2):
        _interrupt(tmp_path, name, seed)


@pytest.mark.slow
@pytest.mark.timeout(1200)
@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_interrupted_at_random_moments_many_times(tmp_path, name):
    for seed in range(2, 12):
        _interrupt(tmp_path, name, seed)


@pytest.mark.timeout(120)
@pytest.mark.parametrize("how", HOW)
def test_covnet_run_interrupted_while_its_metrics_run_in_forks(tmp_path, how):
    """``covnet run`` computes its metrics in forks of itself: interrupted while they run (a
    Ctrl-C to the group, SIGINT or SIGTERM to the command alone), it exits 130 at once, writes
    nothing, prints no traceback, and no fork is left."""
    out = tmp_path / "run"
    p = CovnetProcess(["run", str(REPO / "configs" / "large.yaml"), "--out", str(out)])
    tree = Descendants(p.proc.pid)
    try:  # once the forks are running
        rc, took = _stop_when(p, lambda: any(pp == p.proc.pid for pp, _ in _procs().values()), how)
    finally:
        p.stop()
    text = p.output()
    assert rc == 130, text
    assert took < 5.0 and "Traceback" not in text, text
    assert "nothing written" in text, text
    assert not tree.alive()
    assert not (out / "summary.json").exists()


def _launchers() -> dict[str, list[str]]:
    """How a user starts covnet: ``python -m covnet`` and the console script (what
    pyproject.toml's entry point makes of ``covnet``: import the function, exit with it)."""
    import sys
    import tomllib

    spec = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]["covnet"]
    module, func = spec.split(":")
    script = f"import sys; from {module} import {func}; sys.exit({func}())"
    return {"-m covnet": [sys.executable, "-m", "covnet"], "script": [sys.executable, "-c", script]}


def test_the_command_imports_nothing_more_before_its_signal_handlers():
    """What ``covnet`` (``python -m covnet`` and the console script alike) imports before
    :func:`covnet.__main__.entry` installs the handlers is a window in which a Ctrl-C is a
    traceback: only covnet's package and its interrupt handling.  ``covnet.code_identity``
    there (hashlib and OpenSSL's library, for ``packages_root``) made it wide enough for the
    start-up Ctrl-C test to land in it beside two busy loops (exit -2, a KeyboardInterrupt
    traceback)."""
    import subprocess
    import sys

    probe = (
        "import sys; import covnet.__main__; "
        "print(sorted(m for m in sys.modules if m.startswith('covnet')), 'hashlib' in sys.modules)"
    )
    out = subprocess.run(
        [sys.executable, "-c", probe], cwd=REPO, capture_output=True, text=True, check=True
    ).stdout.strip()
    assert out == (
        "['covnet', 'covnet.__main__', 'covnet.blas_kernel', 'covnet.processes', "
        "'covnet.processes.interrupts'] False"
    ), out


def _covnet_began(pid: int) -> bool:
    """covnet's own first import has begun: ``covnet/__init__`` loads ctypes (to pin the BLAS
    kernel) as its first act, which nothing before it in the interpreter's start-up loads.
    Before that point no code of covnet runs, so no code of covnet can answer a signal."""
    try:
        return "_ctypes" in Path(f"/proc/{pid}/maps").read_text()
    except OSError:
        return True  # gone already: its status says what happened


@pytest.mark.timeout(240)
@pytest.mark.parametrize("launcher", ["-m covnet", "script"])
def test_a_ctrl_c_while_covnet_starts_ends_130_without_a_traceback(tmp_path, launcher):
    """A Ctrl-C or SIGTERM while ``covnet run`` is still importing (its first 0.4 s): exit
    130 (or 0 if it had finished), never a KeyboardInterrupt traceback or death by the signal
    (-2).  The moments are seeded, from when covnet's own first import begins."""
    import subprocess

    argv = _launchers()[launcher]
    rng = random.Random(f"start-up-{launcher}")
    for i in range(8):
        sig = rng.choice((signal.SIGINT, signal.SIGTERM))
        delay = rng.uniform(0.02, 0.4)
        where = f"{launcher}, sample {i}: {sig.name} {delay:.3f} s after covnet began"
        cmd = [*argv, "run", PAPER, "--no-figures", "--out", str(tmp_path / f"run{i}")]
        proc = subprocess.Popen(
            cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        try:
            deadline = time.monotonic() + 30
            while not _covnet_began(proc.pid):
                assert time.monotonic() < deadline, f"{where}: covnet never began"
                time.sleep(0.001)
            time.sleep(delay)  # the seeded moment itself (the condition was waited for above)
            proc.send_signal(sig)
            _, err = proc.communicate(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
        assert proc.returncode in (130, 0), f"{where}: exit {proc.returncode}\n{err}"
        assert "Traceback" not in err, f"{where}: a traceback\n{err}"
        if proc.returncode == 130:
            assert "interrupted" in err, f"{where}: {err}"


def _interrupt_start_up(tmp_path: Path, seed: int) -> None:
    """A Ctrl-C to ``covnet up``'s group at a seeded moment 0-120 ms after its first node
    process appears (while it starts the others); every node process it ever had must be in
    ``processes.json`` and gone when it has exited."""
    delay = random.Random(f"start-up-{seed}").uniform(0.0, 0.12)
    where = f"seed {seed}: group SIGINT {delay * 1e3:.0f} ms after the first node process"
    out = tmp_path / f"start-up-{seed}"
    p = CovnetProcess(["up", PAPER, "--out", str(out)])
    tree = Descendants(p.proc.pid)
    try:
        deadline = time.monotonic() + 60
        while not any(pp == p.proc.pid for pp, _ in _procs().values()):  # the first node
            assert p.proc.poll() is None and time.monotonic() < deadline, p.output()
            time.sleep(0.005)
        time.sleep(delay)  # the random moment itself (the condition was waited for above)
        rc, took = _stop(p, "group-sigint")
    finally:
        p.stop()
    left = tree.alive()
    text = p.output()
    assert rc in (130, 0), f"{where}: exit {rc}\n{text}"
    assert took < 15.0, f"{where}: took {took:.1f} s to stop"
    assert "Traceback" not in text, f"{where}: a traceback\n{text}"
    assert not left, f"{where}: processes left: {left}\n{text}"
    pids_file = out / "processes.json"
    recorded = json.loads(pids_file.read_text()) if pids_file.is_file() else {}
    recorded_pids = {v for v in recorded.values() if isinstance(v, int)}
    started = {pid for pid in tree.seen if tree.parent[pid] == p.proc.pid} - recorded_pids
    assert not started, f"{where}: started but not in processes.json: {started} ({recorded})"


@pytest.mark.timeout(300)
def test_interrupted_while_up_starts_its_nodes(tmp_path):
    for seed in range(4):
        _interrupt_start_up(tmp_path, seed)


@pytest.mark.slow
@pytest.mark.timeout(1200)
def test_interrupted_while_up_starts_its_nodes_many_times(tmp_path):
    for seed in range(4, 24):
        _interrupt_start_up(tmp_path, seed)


@pytest.mark.timeout(120)
def test_ctrl_c_before_ready_is_an_interruption_and_replay_says_there_is_nothing(tmp_path):
    """A Ctrl-C to ``covnet up``'s group once its manager listens, before the network is
    READY: exit 130, ``run.json`` says ``interrupted`` (not ``failed``), nothing is left, and
    ``covnet replay`` says that no scan was done (exit 2), not that a file is missing."""
    out = tmp_path / "run"
    p = CovnetProcess(["up", PAPER, "--out", str(out)])
    tree = Descendants(p.proc.pid)
    try:
        assert p.wait_for("[manager] LISTENING", timeout=60), p.output()
        assert "[manager] READY" not in p.output(), p.output()
        rc, _ = _stop(p, "group-sigint")
    finally:
        p.stop()
    text = p.output()
    assert rc == 130, text
    assert "Traceback" not in text, text
    left = tree.alive()
    assert not left, f"left: {tree.describe(left)}\n{text}"
    info = json.loads((out / "run.json").read_text())
    assert info["status"] == "interrupted", info
    rp = CovnetProcess(["replay", str(out)])
    try:
        rrc = rp.wait(timeout=60)
    finally:
        rp.stop()
    said = rp.output()
    assert "missing" not in said and "Traceback" not in said, said
    if "[manager] READY" in text:  # the network became ready as the Ctrl-C went (a slow machine)
        assert rrc in (0, 2), f"{said}\n{info}\n{text}"
        return
    assert rrc == 2, f"{said}\n{info}\n{text}"
    assert "nothing to replay" in said and "before its first scan" in said, said


@pytest.mark.timeout(120)
@pytest.mark.parametrize("how", ["group-sigint", "sigterm"])
def test_bench_up_interrupted_while_its_network_runs(how, tmp_path, monkeypatch):
    """A Ctrl-C or SIGTERM while ``covnet bench up`` runs its network: the run stops and so does
    the bench, exit 130 with ``interrupted``, not a failed run's status and log; nothing left
    running.  The signal comes once the run's ``live.json`` exists (the network is up and
    scanning; its 200 scans take about a second more)."""
    monkeypatch.setenv("TMPDIR", str(tmp_path))  # the bench's run directories, to watch
    p = CovnetProcess(["bench", "up", "--sensors", "64", "--repeat", "1"])
    tree = Descendants(p.proc.pid)
    try:
        rc, took = _stop_when(
            p, lambda: bool(list(tmp_path.glob("covnet-bench-up-*/run-64-0/live.json"))), how
        )
    finally:
        p.stop()
    text = p.output()
    assert rc == 130, text
    assert took < 10.0
    assert "covnet: error: interrupted" in text and "failed (status" not in text, text
    assert "Traceback" not in text
    assert not tree.alive()
