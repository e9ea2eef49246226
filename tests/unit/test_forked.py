"""Node processes forked from the launcher (covnet.processes.forked, Supervisor with ``preload``):
each
child is what ``python -m MODULE ARGS`` would be (its argv, environment, own session and
process group, stdin closed, output through the pipe, its exit status, death by SIGINT), it
has the preloaded modules without importing them, and the parent's exit work never runs in it.

The supervisor forks only from a process with one thread, so each case runs in a fresh child
interpreter (a process with another thread gets new interpreters, which the last test checks)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import pytest

pytestmark = pytest.mark.timeout(60)

CHILD_MODULE = """
import atexit, os, sys, threading, time
print("argv", sys.argv[1:], flush=True)
print("env", os.environ.get("FOO"), os.environ.get("PYTHONUNBUFFERED"), flush=True)
print("preloaded", "fork_heavy" in sys.modules and sys.modules["fork_heavy"].LOADED_IN, flush=True)
print("group", os.getpgid(0) == os.getpid() == os.getsid(0), flush=True)
print("stdin", repr(sys.stdin.read()), flush=True)
print("name", __name__, open("/proc/self/comm").read().strip(), flush=True)
here = os.environ["MARKS"]
atexit.register(lambda: open(os.path.join(here, f"child-atexit-{sys.argv[1]}"), "w").close())
what = sys.argv[1]
if what == "fail":
    raise ValueError("a defect in the child")
if what == "exit3":
    sys.exit(3)
if what == "wait":
    print("READY", flush=True)
    time.sleep(30)
"""

PARENT = """
import atexit, json, os, sys, tempfile
sys.path.insert(0, {moddir!r})
from covnet.processes.launch import ProcessSpec, Supervisor
from covnet.processes import forked
here = os.environ["MARKS"]
atexit.register(lambda: open(os.path.join(here, f"parent-atexit-{{os.getpid()}}"), "w").close())
keep = tempfile.TemporaryDirectory(dir=here)  # a finalizer the children must not run
pre = ("fork_heavy",)
mk = lambda name, *args: ProcessSpec(
    name, [sys.executable, "-m", "fork_child", *args], env={{"FOO": "bar"}}, preload=pre
)
specs = [mk("a", "ok"), mk("b", "fail"), mk("c", "exit3"), mk("d", "wait")]
lines = []
with Supervisor(specs, on_line=lambda n, l: lines.append([n, l])) as sup:
    kinds = {{n: type(r.proc).__name__ for n, r in sup._runs.items()}}
    ready = sup.wait_for_line("d", "READY", 20)
    rcs = {{n: sup.wait(n, 20) for n in "abc"}}
    final = sup.stop()
print(json.dumps({{"kinds": kinds, "ready": ready, "rcs": rcs, "final": final,
                  "lines": lines, "parent": os.getpid(), "tmp": os.path.isdir(keep.name)}}))
"""


@pytest.fixture()
def modules(tmp_path: Path) -> Path:
    d = tmp_path / "mods"
    d.mkdir()
    (d / "fork_child.py").write_text(CHILD_MODULE)
    (d / "fork_heavy.py").write_text("import os\nLOADED_IN = os.getpid()\n")
    return d


def _parent(tmp_path: Path, modules: Path) -> dict:
    marks = tmp_path / "marks"
    marks.mkdir()
    done = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(PARENT.format(moddir=str(modules)))],
        capture_output=True,
        text=True,
        timeout=50,
        env={**os.environ, "MARKS": str(marks)},
    )
    assert done.returncode == 0, done.stdout + done.stderr
    out = json.loads(done.stdout.strip().splitlines()[-1])
    out["marks"] = sorted(p.name for p in marks.iterdir())
    return out


def test_forked_children_are_what_python_m_would_be(tmp_path, modules):
    got = _parent(tmp_path, modules)
    assert set(got["kinds"].values()) == {"ForkedProcess"}
    assert got["ready"]
    lines: dict[str, list[str]] = {}
    for name, line in got["lines"]:
        lines.setdefault(name, []).append(line)
    for name, arg in (("a", "ok"), ("b", "fail"), ("c", "exit3"), ("d", "wait")):
        out = lines[name]
        assert out[0] == f"argv ['{arg}']"
        assert out[1] == "env bar 1"
        assert out[2] == f"preloaded {got['parent']}"  # imported once, in the parent
        assert out[3] == "group True"
        assert out[4] == "stdin ''"
        assert out[5] == f"name __main__ covnet-{name}"
    assert got["rcs"] == {"a": 0, "b": 1, "c": 3}
    assert "ValueError: a defect in the child" in lines["b"]  # its traceback, in its output
    assert got["final"]["d"] == -2  # an uncaught KeyboardInterrupt: death by SIGINT
    # the children's own exit work ran; the parent's ran once, in the parent, and the
    # parent's temporary directory outlived its children
    assert {"child-atexit-ok", "child-atexit-fail", "child-atexit-exit3"} <= set(got["marks"])
    assert [m for m in got["marks"] if m.startswith("parent-atexit")] == [
        f"parent-atexit-{got['parent']}"
    ]
    assert got["tmp"] is True


def test_a_process_with_threads_starts_new_interpreters(modules, monkeypatch, tmp_path):
    from covnet.processes.launch import ProcessSpec, Supervisor

    monkeypatch.syspath_prepend(str(modules))
    monkeypatch.setenv("MARKS", str(tmp_path))
    monkeypatch.setenv("PYTHONPATH", str(modules))
    spec = ProcessSpec("a", [sys.executable, "-m", "fork_child", "ok"], preload=("fork_heavy",))
    done = threading.Event()
    other = threading.Thread(target=done.wait)  # a second thread: no fork
    other.start()
    try:
        with Supervisor([spec], on_line=lambda n, line: None) as sup:
            assert type(sup._runs["a"].proc).__name__ == "Popen"
            assert sup.wait("a", 30) == 0
    finally:
        done.set()
        other.join()


def test_no_fork_once_a_zenoh_runtime_has_run():
    """zenoh's runtime threads outlive its sessions; a fork would inherit its state without
    them (a hang), so a process that has opened a session starts new interpreters."""
    code = (
        "from covnet.processes import forked\n"
        "from covnet.wire.zenoh_bus import ZenohBus, zenoh_config\n"
        "before = forked.forkable()\n"
        "ZenohBus.open(zenoh_config('router', listen=['tcp/127.0.0.1:0'])).close()\n"
        "print(before, forked.forkable())\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=50)
    assert done.stdout.split() == ["True", "False"], done.stdout + done.stderr


PKG_MAIN = """
import warnings
warnings.warn("a warning of the child", UserWarning)
if __name__ == "__main__":
    print("pkg main ran", flush=True)
"""

PARENT_WITH_STATE = """
import sys, warnings
sys.path.insert(0, {moddir!r})
warnings.simplefilter("error")  # a test runner's filter: not the child's
warnings.simplefilter("ignore")  # (importing the __main__ below warns here)
import fork_pkg.__main__  # the parent has imported the module the child runs as __main__
warnings.simplefilter("error")
from covnet.processes.launch import ProcessSpec, Supervisor
lines = []
spec = ProcessSpec("p", [sys.executable, "-m", "fork_pkg"], preload=("fork_heavy",))
with Supervisor([spec], on_line=lambda n, l: lines.append(l)) as sup:
    kind = type(sup._runs["p"].proc).__name__
    rc = sup.wait("p", 20)
print(kind, rc, lines)
"""


def test_a_fork_has_a_fresh_interpreters_warnings_and_runs_its_main_afresh(tmp_path, modules):
    """The parent's warning filters (a test runner's ``error``) and a ``MODULE.__main__`` the
    parent imported are not the child's: it warns as ``python -m`` would, and runs."""
    pkg = modules / "fork_pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "__main__.py").write_text(PKG_MAIN)
    done = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(PARENT_WITH_STATE.format(moddir=str(modules)))],
        capture_output=True,
        text=True,
        timeout=50,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    kind, rc, rest = done.stdout.strip().split(" ", 2)
    assert (kind, rc) == ("ForkedProcess", "0"), done.stdout
    assert "pkg main ran" in rest
    assert "UserWarning: a warning of the child" in rest


MAP_SCRIPT = """
import json, os, sys, time
from covnet.processes import forked

def square(x):
    return x * x, os.getpid()

def still_alive(pids):  # the processes of pids that still exist (zombies included)
    alive = []
    for p in pids:
        try:
            os.kill(p, 0)
            alive.append(p)
        except ProcessLookupError:
            pass
    return alive

what = sys.argv[1]
if what == "map":
    out = forked.map_in_forks(square, [1, 2, 3, 4])
    print(json.dumps({"values": [v for v, _ in out], "pids": [p for _, p in out],
                      "me": os.getpid(), "forkable": forked.forkable()}))
elif what == "fail":
    def fail_on_two(x):
        if x == 2:
            raise ValueError("item two is bad")
        return x
    try:
        forked.map_in_forks(fail_on_two, [1, 2, 3])
    except ValueError as exc:
        print(json.dumps({"raised": str(exc)}))
elif what == "interrupt":
    marks = sys.argv[2]
    def slow_or_interrupted(x):
        if x == "last":
            while len(os.listdir(marks)) < 2:  # both children started
                time.sleep(0.01)
            raise KeyboardInterrupt
        open(os.path.join(marks, str(os.getpid())), "w").close()
        time.sleep(60)
    try:
        forked.map_in_forks(slow_or_interrupted, ["a", "b", "last"])
    except KeyboardInterrupt:
        pids = [int(p) for p in os.listdir(marks)]
        print(json.dumps({"children": len(pids), "alive": still_alive(pids)}))
elif what == "signal_at_fork":
    # a Ctrl-C to the group at the moment of the fork: parent and child each get one
    import signal
    marks, forks = sys.argv[2], []
    signal.signal(signal.SIGINT, signal.default_int_handler)
    real_fork = os.fork
    def fork():
        pid = real_fork()
        if pid:
            forks.append(pid)
        os.kill(os.getpid(), signal.SIGINT)
        return pid
    os.fork = fork
    try:
        forked.map_in_forks(lambda x: time.sleep(60), ["a", "b", "last"])
    except KeyboardInterrupt:  # whoever gets here writes a mark: only the parent should
        open(os.path.join(marks, str(os.getpid())), "w").close()
    alive = still_alive(forks)
    time.sleep(0.5)  # a child that unwound this code would have written its mark by now
    if forks:
        print(json.dumps({"me": os.getpid(), "forks": len(forks), "alive": alive,
                          "marks": sorted(int(m) for m in os.listdir(marks))}))
"""


def _map_case(tmp_path, *args, env=None):
    script = tmp_path / "map_case.py"
    script.write_text(MAP_SCRIPT)
    out = subprocess.run(
        [sys.executable, str(script), *args],
        capture_output=True,
        text=True,
        timeout=60,
        # this checkout's covnet, whatever the installed one is
        env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2]), **(env or {})},
        check=True,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_map_in_forks_computes_each_item_in_its_own_fork_in_order(tmp_path):
    got = _map_case(tmp_path, "map")
    assert got["values"] == [1, 4, 9, 16]
    if not got["forkable"] or (os.cpu_count() or 1) < 2:
        pytest.skip("no fork here (threads, one core)")
    assert got["pids"][-1] == got["me"]  # the last item here
    assert len(set(got["pids"][:-1])) == 3 and got["me"] not in got["pids"][:-1]


def test_map_in_forks_without_forking_when_told_so(tmp_path):
    got = _map_case(tmp_path, "map", env={"COVNET_FORK": "0"})
    assert got["values"] == [1, 4, 9, 16] and set(got["pids"]) == {got["me"]}


def test_an_exception_in_a_forked_item_is_raised_in_the_parent(tmp_path):
    assert _map_case(tmp_path, "fail") == {"raised": "item two is bad"}


def test_an_interrupted_map_leaves_no_child_running(tmp_path):
    if (os.cpu_count() or 1) < 2:
        pytest.skip("one core: nothing is forked")
    marks = tmp_path / "marks"
    marks.mkdir()
    got = _map_case(tmp_path, "interrupt", str(marks))
    assert got == {"children": 2, "alive": []}


def test_a_ctrl_c_at_the_moment_of_a_fork_leaves_no_child_and_no_second_caller(tmp_path):
    """A SIGINT between the fork and the child's registration lost the child (never killed),
    and one in the child before it reached its own code unwound the caller's code in the child
    (``covnet run``'s forks outlived the command, exit 130 printed twice)."""
    if (os.cpu_count() or 1) < 2:
        pytest.skip("one core: nothing is forked")
    marks = tmp_path / "marks"
    marks.mkdir()
    got = _map_case(tmp_path, "signal_at_fork", str(marks))
    assert got["forks"] == 1 and got["alive"] == []
    assert got["marks"] == [got["me"]], got


def test_covnet_run_forks_its_metrics_and_gives_the_one_process_results(tmp_path, paper_path):
    """Each metric of ``covnet run`` in its own fork: bit for bit what one process computes."""
    out = {}
    for fork in ("1", "0"):
        d = tmp_path / f"run-{fork}"
        argv = ["run", str(paper_path), "--no-figures", "--out", str(d)]
        subprocess.run(
            [sys.executable, "-m", "covnet", *argv],
            capture_output=True,
            text=True,
            timeout=120,
            env={**os.environ, "COVNET_FORK": fork},
            check=True,
        )
        out[fork] = d
    import numpy as np

    assert (out["1"] / "summary.json").read_bytes() == (out["0"] / "summary.json").read_bytes()
    a, b = np.load(out["1"] / "arrays.npz"), np.load(out["0"] / "arrays.npz")
    assert a.files == b.files
    for k in a.files:
        if not k.startswith("decision_s"):  # wall-clock times
            assert a[k].tobytes() == b[k].tobytes(), k
