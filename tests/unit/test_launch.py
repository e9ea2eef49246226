"""The process supervisor, with tiny ``python -c`` children. Every wait is on a condition (a
line, an exit), bounded by a timeout; nothing is left running."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import threading

import pytest

from covnet.processes.launch import EXIT_RUN_FAILED, ProcessSpec, Supervisor

pytestmark = pytest.mark.timeout(60)

PY = sys.executable

# a child that prints READY once its handlers are in place, then waits to be stopped
POLITE = """
import signal, sys, time
print("hello", flush=True)
print("oops", file=sys.stderr, flush=True)
try:  # READY only once inside the try: a SIGINT right after READY is still caught
    print("READY", flush=True)
    time.sleep(60)
except KeyboardInterrupt:
    print("bye", flush=True)
    sys.exit(0)
"""
DEAF_TO_SIGINT = """
import signal, time
signal.signal(signal.SIGINT, signal.SIG_IGN)
print("READY", flush=True)
time.sleep(60)
"""
DEAF_TO_BOTH = """
import signal, time
signal.signal(signal.SIGINT, signal.SIG_IGN)
signal.signal(signal.SIGTERM, signal.SIG_IGN)
print("READY", flush=True)
time.sleep(60)
"""
GRANDCHILD = (
    "import signal, time; signal.signal(signal.SIGINT, signal.SIG_IGN); "
    "print('G', flush=True); time.sleep(60)"
)
WITH_GRANDCHILD = f"""
import subprocess, sys, time
g = subprocess.Popen([sys.executable, "-c", {GRANDCHILD!r}])
print("GRANDCHILD", g.pid, flush=True)
print("READY", flush=True)
time.sleep(60)
"""


def _running(pid: int) -> bool:
    """Whether ``pid`` is a live (non-zombie) process."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def _assert_all_gone(pids):
    for pid in pids:
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)  # reaped: the pid no longer exists


class Lines:
    def __init__(self):
        self.lines: list[tuple[str, str]] = []
        self._lock = threading.Lock()

    def __call__(self, name, line):
        with self._lock:
            self.lines.append((name, line))


def test_ready_output_and_pids_file(tmp_path, capsys):
    pids_file = tmp_path / "pids.json"
    specs = [ProcessSpec("a", [PY, "-c", POLITE]), ProcessSpec("b", [PY, "-c", POLITE])]
    with Supervisor(specs, pids_file=pids_file) as sup:
        pids = json.loads(pids_file.read_text())  # written as soon as they start
        assert pids == sup.pids and set(pids) == {"a", "b"}
        assert sup.wait_for_line("a", "READY", timeout=20)
        assert sup.wait_for_line("b", lambda line: line == "READY", timeout=20)
        assert sup.poll() == {"a": None, "b": None}
        assert sup.output("a") == ["hello", "oops", "READY"]  # stderr merged, in order
        codes = sup.stop()
    assert codes == {"a": 0, "b": 0}  # SIGINT -> KeyboardInterrupt -> clean exit
    out = capsys.readouterr().out
    for name in "ab":
        for line in ("hello", "oops", "READY", "bye"):
            assert f"[{name}] {line}\n" in out
    _assert_all_gone(pids.values())


def test_on_line_and_environment():
    sink = Lines()
    code = "import os; print(os.environ['PYTHONUNBUFFERED'], os.environ['COVNET_X'])"
    spec = ProcessSpec("env", [PY, "-c", code], env={"COVNET_X": "42"})
    with Supervisor([spec], on_line=sink) as sup:
        assert sup.wait_for_line("env", "1 42", timeout=20)
        assert sup.wait("env", timeout=20) == 0
    assert sink.lines == [("env", "1 42")]


def test_wait_for_line_gives_up_on_exit_and_on_timeout():
    specs = [
        ProcessSpec("quits", [PY, "-c", "print('nope')"]),
        ProcessSpec("silent", [PY, "-c", POLITE]),
    ]
    with Supervisor(specs, on_line=Lines()) as sup:
        assert not sup.wait_for_line("quits", "READY", timeout=30)  # returns at EOF, not 30 s
        assert sup.wait("quits", timeout=20) == 0
        assert sup.wait_for_line("silent", "READY", timeout=20)
        assert not sup.wait_for_line("silent", "never printed", timeout=0.2)
        assert sup.poll() == {"quits": 0, "silent": None}


def test_escalation_sigint_then_sigterm_then_sigkill():
    specs = [
        ProcessSpec("polite", [PY, "-c", POLITE]),
        ProcessSpec("deaf1", [PY, "-c", DEAF_TO_SIGINT]),
        ProcessSpec("deaf2", [PY, "-c", DEAF_TO_BOTH]),
    ]
    # SIGINT's wait is generous: under load a polite child may need over a second to run its
    # handler (a 0.3-0.5 s wait failed in CI); the deaf ones just wait it out
    with Supervisor(specs, on_line=Lines(), sigint_timeout=5.0, sigterm_timeout=1.0) as sup:
        for spec in specs:
            assert sup.wait_for_line(spec.name, "READY", timeout=20)
        pids = sup.pids
        codes = sup.stop()
    assert codes == {"polite": 0, "deaf1": -signal.SIGTERM, "deaf2": -signal.SIGKILL}
    assert sup.stop() == codes  # idempotent: nothing is signalled again
    _assert_all_gone(pids.values())


def test_stop_kills_the_whole_process_group():
    sink = Lines()
    with Supervisor([ProcessSpec("p", [PY, "-c", WITH_GRANDCHILD])], on_line=sink) as sup:
        assert sup.wait_for_line("p", "READY", timeout=20)
        assert sup.wait_for_line("p", "G", timeout=20)
        (grandchild,) = [int(line.split()[1]) for _, line in sink.lines if line.startswith("GRAND")]
        assert _running(grandchild)
        sup.stop(sigint_timeout=2.0, sigterm_timeout=2.0)
    assert not _running(grandchild)


def test_restart_by_hand_and_automatic(tmp_path):
    pids_file = tmp_path / "pids.json"
    specs = [
        ProcessSpec("manual", [PY, "-c", POLITE]),
        ProcessSpec("auto", [PY, "-c", "print('READY'); raise SystemExit(5)"], restart=True),
        ProcessSpec("once", [PY, "-c", "raise SystemExit(4)"]),
        ProcessSpec("clean", [PY, "-c", "raise SystemExit(0)"], restart=True),
        # left because its run did not end well: there is no run to rejoin
        ProcessSpec("over", [PY, "-c", f"raise SystemExit({EXIT_RUN_FAILED})"], restart=True),
    ]
    with Supervisor(specs, on_line=Lines(), pids_file=pids_file) as sup:
        assert sup.wait_for_line("manual", "READY", timeout=20)
        old = sup.pids
        sup.restart("manual")
        assert sup.pids["manual"] != old["manual"]
        assert sup.wait_for_line("manual", "READY", timeout=20)  # the new incarnation's
        assert json.loads(pids_file.read_text())["manual"] == sup.pids["manual"]

        assert sup.wait("auto", timeout=20) == 5
        assert sup.wait("once", timeout=20) == 4
        assert sup.wait("clean", timeout=20) == 0
        assert sup.wait("over", timeout=20) == EXIT_RUN_FAILED
        status = sup.poll()  # restarts "auto" (failed), not "once" (no policy), not "clean"
        assert status["auto"] is None and status["once"] == 4 and status["clean"] == 0
        assert status["over"] == EXIT_RUN_FAILED
        assert sup.restarts == {"manual": 1, "auto": 1, "once": 0, "clean": 0, "over": 0}
        assert sup.pids["auto"] != old["auto"]
        assert json.loads(pids_file.read_text()) == sup.pids
        assert sup.wait_for_line("auto", "READY", timeout=20)
        all_pids = set(old.values()) | set(sup.pids.values())
    _assert_all_gone(all_pids)


def test_bad_specs():
    with pytest.raises(ValueError, match="duplicate"):
        Supervisor([ProcessSpec("a", [PY]), ProcessSpec("a", [PY])])
    with pytest.raises(ValueError, match="empty argv"):
        Supervisor([ProcessSpec("a", [])])


def test_a_failed_start_stops_the_started_ones():
    sink = Lines()
    specs = [
        ProcessSpec("ok", [PY, "-c", POLITE]),
        ProcessSpec("missing", ["/nonexistent/covnet-test-binary"]),
    ]
    sup = Supervisor(specs, on_line=sink, sigint_timeout=2.0)
    with pytest.raises(FileNotFoundError):
        sup.start()
    pid = sup.pids["ok"]
    assert sup.poll()["ok"] is not None
    _assert_all_gone([pid])


# a parent process that supervises children the way `covnet up` will
PARENT = textwrap.dedent(
    """
    import sys, time
    from pathlib import Path
    from covnet.processes.launch import ProcessSpec, Supervisor, sigterm_raises_keyboard_interrupt
    sigterm_raises_keyboard_interrupt()
    polite, deaf, pids_file, fail = sys.argv[1], sys.argv[2], Path(sys.argv[3]), sys.argv[4]
    specs = [ProcessSpec("polite", [sys.executable, "-c", polite]),
             ProcessSpec("deaf", [sys.executable, "-c", deaf])]
    with Supervisor(specs, pids_file=pids_file, sigint_timeout=5.0, sigterm_timeout=1.0) as sup:
        assert sup.wait_for_line("polite", "READY", 20) and sup.wait_for_line("deaf", "READY", 20)
        print("PARENT READY", flush=True)
        if fail == "raise":
            raise RuntimeError("boom")
        time.sleep(60)
    """
)


@pytest.mark.parametrize(
    ("how", "expected_rc"),
    # an uncaught KeyboardInterrupt ends Python by re-raising SIGINT: returncode -2
    [("sigint", -signal.SIGINT), ("sigterm", -signal.SIGINT), ("raise", 1)],
    ids=["ctrl-c", "sigterm", "exception"],
)
def test_parent_interrupted_or_failing_leaves_nothing_running(tmp_path, how, expected_rc):
    pids_file = tmp_path / "pids.json"
    argv = [PY, "-c", PARENT, POLITE, DEAF_TO_SIGINT, str(pids_file), how]
    parent = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        lines = []
        for line in parent.stdout:  # bounded by the test timeout
            lines.append(line)
            if "PARENT READY" in line:
                break
        assert any("PARENT READY" in line for line in lines), lines
        if how == "sigint":
            parent.send_signal(signal.SIGINT)
        elif how == "sigterm":
            parent.send_signal(signal.SIGTERM)
        rest = parent.communicate(timeout=20)[0]
        assert parent.returncode == expected_rc, rest
        assert "[polite] bye" in rest  # the polite child was stopped with SIGINT
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait()
    pids = json.loads(pids_file.read_text())
    assert set(pids) == {"polite", "deaf"}
    for pid in pids.values():
        assert not _running(pid)


# a parent whose Ctrl-C lands right after a child was created, before start() has recorded it
# (the wrapped spawn raises the signal at once: its handler runs before the spawn returns)
INTERRUPTED_START = textwrap.dedent(
    """
    import json, signal, sys
    from pathlib import Path
    from covnet.processes import forked, interrupts
    from covnet.processes.launch import ProcessSpec, Supervisor
    signal.signal(signal.SIGINT, interrupts.raise_interrupt)
    how, at, pids_file, started_file = sys.argv[1:5]
    started = []

    def landing(real):
        def spawn(*args, **kwargs):
            proc = real(*args, **kwargs)
            started.append(proc.pid)
            Path(started_file).write_text(json.dumps(started))
            if len(started) == int(at):
                signal.raise_signal(signal.SIGINT)
            return proc
        return spawn

    if how == "fork":
        forked.fork_module = landing(forked.fork_module)
    elif how == "popen":
        Supervisor._popen = staticmethod(landing(Supervisor._popen))
    else:  # "pids": a Ctrl-C as the pids file is written once every reader runs (if it is)
        Supervisor._popen = staticmethod(landing(Supervisor._popen))
        real_write, real_reader, readers = Supervisor._write_pids, Supervisor._start_reader, []
        def reader(self, name, run):
            real_reader(self, name, run)
            readers.append(name)
        def write(self):
            real_write(self)
            if len(readers) == 3 and not getattr(self, "hit", False):
                self.hit = True
                signal.raise_signal(signal.SIGINT)
        Supervisor._write_pids, Supervisor._start_reader = write, reader
        at = "99"  # the spawns themselves are not interrupted
    pre = ("json",) if how == "fork" else ()
    specs = [ProcessSpec(n, [sys.executable, "-m", "child_mod"], preload=pre) for n in "abc"]
    sup = Supervisor(specs, pids_file=Path(pids_file), on_line=lambda n, l: None,
                     sigint_timeout=2.0, sigterm_timeout=2.0)
    try:
        sup.start()
    except KeyboardInterrupt:
        print("INTERRUPTED", json.dumps(sup.pids), flush=True)
        sys.exit(0)
    print("STARTED", flush=True)
    sup.stop()
    """
)


@pytest.mark.parametrize(
    ("how", "at"), [(h, n) for h in ("fork", "popen") for n in (1, 2, 3)] + [("pids", 3)]
)
def test_a_ctrl_c_between_fork_and_record_leaves_no_child(tmp_path, how, at):
    """A Ctrl-C that lands just after a child is created, before the supervisor has recorded
    it (or as it writes the pids file: ``pids``): start() stops on the KeyboardInterrupt, every
    child it created is in the pids file and stopped (a user saw a sensor of ``covnet up`` left
    running after such a Ctrl-C)."""
    (tmp_path / "child_mod.py").write_text(POLITE)
    pids_file, started_file = tmp_path / "pids.json", tmp_path / "started.json"
    argv = [PY, "-c", INTERRUPTED_START, how, str(at), str(pids_file), str(started_file)]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), *sys.path])}
    started: list[int] = []
    try:
        done = subprocess.run(argv, capture_output=True, text=True, timeout=40, env=env)
        started = json.loads(started_file.read_text())
        said = done.stdout + done.stderr
        if how == "pids":  # interrupted or not, nothing may be left
            assert done.returncode == 0 and ("INTERRUPTED" in said or "STARTED" in said), said
        else:
            assert done.returncode == 0 and "INTERRUPTED" in said, said
        assert len(started) == at, (started, done.stdout)
        recorded = json.loads(pids_file.read_text())
        assert set(started) <= set(recorded.values()), (started, recorded)
        left = [pid for pid in started if _running(pid)]
        assert not left, f"children left running: {left}"
    finally:
        for pid in started:  # on a failure, nothing stays behind
            try:
                os.killpg(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass


def test_a_node_gone_before_ready_is_named_unless_it_left_with_the_run():
    """Before READY the launcher fails at once naming a node that ended for good.  A node that
    found no run to join (EXIT_NO_RUN) is not restarted, so it is one even when restartable:
    with ``restart: on-failure`` the launcher said only that the manager failed (hunt 13)."""
    from covnet.processes.launch import EXIT_NO_RUN
    from covnet.processes.up import gone_before_ready

    rcs = {"manager": None, "world": EXIT_NO_RUN, "S1": 1, "S2": EXIT_RUN_FAILED, "S3": 0}
    assert gone_before_ready(rcs, set()) == {"world": EXIT_NO_RUN, "S1": 1}
    # restartable: S1 (a crash) runs again, the world (no run to join) does not
    assert gone_before_ready(rcs, {"world", "S1", "S2", "S3"}) == {"world": EXIT_NO_RUN}
