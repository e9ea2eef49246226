"""Chaos: a real-time ``covnet up`` with ``network.restart: on-failure`` while random sensors,
the world and the recorder are killed with SIGKILL at random (seeded) moments.  The run
completes; no sensor is allocated between its death (plus the detection bound) and its
restart; every restart is in ``run.json``; the directory is valid, and replays exactly unless
the recorder itself was killed (then the replay names the gap and exits 1)."""

from __future__ import annotations

import json
import os
import random
import signal
import threading
import time
from collections import Counter
from pathlib import Path

import pytest
import yaml
from multiproc import CovnetProcess, assert_nothing_left

from covnet.runs.recording import read_recording
from covnet.wire import messages as msg

pytestmark = [pytest.mark.integration]

DETECT_S = 0.3
"""A killed sensor's token is gone within milliseconds on loopback; the manager checks
membership at every scan (0.1 s at --speed 10): from then on it must not allocate it."""


class PidWatch:
    """The launcher's processes.json, polled: every pid each process had, first seen when."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.history: dict[str, list[tuple[int, int]]] = {}  # name -> [(pid, seen_ns)]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._poll, daemon=True)
        self._thread.start()

    def _poll(self) -> None:
        while not self._stop.is_set():
            try:
                pids = json.loads(self.path.read_text())
            except (OSError, ValueError):
                pids = {}
            now = time.monotonic_ns()
            for name, pid in pids.items():
                if not isinstance(pid, int):  # "hosts": sensor -> its process
                    continue
                seen = self.history.setdefault(name, [])
                if not seen or seen[-1][0] != pid:
                    seen.append((pid, now))
            self._stop.wait(0.01)

    def current(self, name: str) -> int:
        return self.history[name][-1][0]

    def restarted_after(self, name: str, t_ns: int) -> int | None:
        """When a pid of ``name`` first seen after ``t_ns`` was seen (None: never)."""
        return next((seen for _, seen in self.history.get(name, []) if seen > t_ns), None)

    def close(self) -> None:
        self._stop.set()
        self._thread.join()


@pytest.mark.timeout(300)
@pytest.mark.parametrize(
    "seed", [2026, *[pytest.param(s, marks=pytest.mark.slow) for s in range(1, 9)]]
)
def test_chaos_run_completes_and_never_allocates_a_dead_sensor(tmp_path, paper_path, seed):
    data = yaml.safe_load(paper_path.read_text())
    # 15 s of run (speed 10), the kills in its first 6.5 s: a restart (a new interpreter, 1-5 s
    # on a loaded 2-core machine) comes up, and the restarted recorder writes its segment,
    # before the run ends (the runs ended 5 s late until December 6, which hid a late restart)
    data["scans"] = 150
    data["allocation"]["metrics"] = ["spectral"]
    data.setdefault("network", {})["restart"] = "on-failure"
    cfg = tmp_path / "chaos.yaml"
    cfg.write_text(yaml.safe_dump(data))
    out = tmp_path / "run"
    ids = [s["id"] for s in data["sensors"]]
    rng = random.Random(seed)
    victims = [*(rng.choice(ids) for _ in range(4)), "world", "recorder"]
    rng.shuffle(victims)
    at = sorted(rng.uniform(0.5, 6.5) for _ in victims)  # seconds after READY (run: 15 s)

    p = CovnetProcess(["up", str(cfg), "--realtime", "--speed", "10", "--out", str(out)])
    kills: list[tuple[str, int, int]] = []  # (name, pid, t_kill_ns)
    watch = None
    try:
        assert p.wait_for("[manager] READY", timeout=60), p.output()
        t0 = time.monotonic()
        watch = PidWatch(out / "processes.json")
        for name, t in zip(victims, at, strict=True):
            time.sleep(max(0.0, t0 + t - time.monotonic()))  # the seeded moment
            pid = watch.current(name)
            if kills and kills[-1][:2] == (name, pid):
                continue  # not restarted yet: one kill per incarnation
            os.kill(pid, signal.SIGKILL)
            kills.append((name, pid, time.monotonic_ns()))
        rc = p.wait(timeout=120)
    finally:
        if watch is not None:
            watch.close()
        p.stop()
    text = p.output()
    print("kills:", [(n, round((t - kills[0][2]) / 1e9, 2)) for n, _, t in kills])
    assert rc == 0, text
    assert "Traceback" not in text, text
    assert_nothing_left(out)
    info = json.loads((out / "run.json").read_text())
    assert info["status"] == "completed", info
    assert info["restarts"] == dict(Counter(name for name, _, _ in kills)), (info, kills)
    for f in ("summary.json", "arrays.npz", "config.json", "network.json"):
        assert (out / f).is_file(), f

    # no sensor enabled by a command sent after its death was seen and before it came back
    commands = []
    for s in read_recording(out / "recording.mcap"):  # every segment
        if "/cmd/" in s.key:
            try:
                commands.append(msg.decode_command(s.key, s.payload))
            except msg.WireError:
                continue
    assert commands
    for name, _, t_kill in kills:
        if name not in ids:
            continue
        back = watch.restarted_after(name, t_kill) or time.monotonic_ns()
        bad = [
            c.scan
            for c in commands
            if t_kill + DETECT_S * 1e9 <= c.t_sent_ns <= back and name in c.enabled
        ]
        assert not bad, f"{name} killed, allocated in scans {bad}"

    rp = CovnetProcess(["replay", str(out)])
    try:
        rrc = rp.wait(timeout=120)
    finally:
        rp.stop()
    assert "Traceback" not in rp.output()
    if "recorder" in {n for n, _, _ in kills}:
        assert rrc in (0, 1), rp.output()
        assert (out / "recording.2.mcap").is_file()
    else:
        assert rrc == 0 and "identical" in rp.output(), rp.output()


def _spectral_config(tmp_path, paper_path, name, *, scans=None, restart=None):
    """The paper config with the spectral metric alone (``scans``, ``network.restart``
    changed where given), written to ``tmp_path / name``."""
    data = yaml.safe_load(paper_path.read_text())
    data["allocation"]["metrics"] = ["spectral"]
    if scans is not None:
        data["scans"] = scans
    if restart is not None:
        data.setdefault("network", {})["restart"] = restart
    cfg = tmp_path / name
    cfg.write_text(yaml.safe_dump(data))
    return cfg


@pytest.mark.timeout(180)
@pytest.mark.parametrize("victim", ["world", "recorder"])
def test_a_dead_world_or_recorder_is_not_a_completed_run(tmp_path, paper_path, victim):
    """Without ``restart: on-failure``, the world (the truth) or the recorder SIGKILLed once the
    network is READY and a few scans are done: the manager still does every scan, but the run
    is not complete: exit 1, ``run.json`` says ``failed``, names the node and the scan under
    ``lost``, and ``membership`` (there and in ``network.json``) counts its failure."""
    cfg = _spectral_config(tmp_path, paper_path, "short.yaml", scans=40)
    out = tmp_path / "run"
    p = CovnetProcess(["up", str(cfg), "--realtime", "--speed", "10", "--out", str(out)])
    try:
        assert p.wait_for("[manager] READY", timeout=60), p.output()
        # the plain status lines come once a second: the second one is 10 scans later
        assert p.wait_for(lambda line: line.startswith("[status]") and " scan " in line, 30)
        pid = json.loads((out / "processes.json").read_text())[victim]
        os.kill(pid, signal.SIGKILL)
        rc = p.wait(timeout=120)
    finally:
        p.stop()
    text = p.output()
    assert rc == 1, text
    assert "Traceback" not in text, text
    assert f"the {victim} died (exit status -9)" in text, text
    assert_nothing_left(out)
    info = json.loads((out / "run.json").read_text())
    assert info["status"] == "failed", info
    assert info["scans_completed"] == {"spectral": 40}, info  # the manager did every scan
    (lost,) = info["lost"]
    assert lost["node"] == victim and lost["exit_status"] == -9, lost
    assert lost["after_scan"] is not None and 1 <= lost["after_scan"] < 40, lost
    assert victim in info["ended"], info["ended"]
    assert info["membership"][victim] == {"failed": 1}, info["membership"]
    net = json.loads((out / "network.json").read_text())
    assert net["membership"][victim] == {"failed": 1}, net["membership"]
    assert (out / "summary.json").is_file()
    if victim == "recorder":  # the recording stops there: replay differs, and says why first
        rp = CovnetProcess(["replay", str(out)])
        try:
            rrc = rp.wait(timeout=120)
        finally:
            rp.stop()
        said = rp.output()
        assert rrc == 1 and "the recorder died" in said and "Traceback" not in said, said


@pytest.mark.timeout(120)
def test_restarts_are_in_run_json_also_when_the_run_is_interrupted(tmp_path, paper_path):
    """The launcher printed ``restarted: {'S5': 1}``, but a run then interrupted (Ctrl-C) left
    ``restarts: null`` in run.json: it was written on the normal path only."""
    cfg = _spectral_config(tmp_path, paper_path, "restart.yaml", restart="on-failure")
    out = tmp_path / "run"
    p = CovnetProcess(["up", str(cfg), "--realtime", "--speed", "5", "--out", str(out)])
    try:
        assert p.wait_for("[manager] READY", timeout=60), p.output()
        pid = json.loads((out / "processes.json").read_text())["S5"]
        os.kill(pid, signal.SIGKILL)
        assert p.wait_for("[launcher] restarted: {'S5': 1}", timeout=30), p.output()
        os.killpg(p.proc.pid, signal.SIGINT)  # Ctrl-C: the terminal's whole group
        rc = p.wait(timeout=60)
    finally:
        p.stop()
    assert rc == 130, p.output()
    info = json.loads((out / "run.json").read_text())
    assert info["status"] == "interrupted" and info["restarts"] == {"S5": 1}, info
    assert_nothing_left(out)
