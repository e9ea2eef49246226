"""``covnet up`` from a folder that holds a user's ``sensors.py``, ``manager.py``, ``world.py``
and ``recorder.py``: the nodes are covnet's all the same (``python -m sensors`` puts the working
directory first on ``sys.path``; the launcher under ``python -m covnet`` too).  Hunt 14: the
launcher's preload stopped with ``'sensors' is not a package``; with ``COVNET_FORK=0`` every
node ran the user's module and the manager waited 30 s for nodes that had exited 0; a
restarted sensor (a new interpreter) was the user's module and never came back."""

from __future__ import annotations

import json
import os
import re
import signal

import pytest
import yaml
from multiproc import CovnetProcess, assert_nothing_left

pytestmark = [pytest.mark.integration, pytest.mark.timeout(180)]

ROLES = ("sensors", "manager", "world", "recorder")


def _folder_of_user_modules(tmp_path):
    """A working directory with a harmless module of each node's name (each says so if run)."""
    here = tmp_path / "work"
    here.mkdir()
    for role in ROLES:
        (here / f"{role}.py").write_text(
            f'# my {role} notes\nSITES = {{"north": (0, 1)}}\nprint("the user\'s {role}.py ran")\n'
        )
    return here


def _config(tmp_path, paper_path, **data_over):
    data = yaml.safe_load(paper_path.read_text())
    data.update(data_over)
    path = tmp_path / "paper-short.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def _up(args, cwd, fork="1"):
    return CovnetProcess(args, cwd=cwd, prefix=["env", f"COVNET_FORK={fork}"])


@pytest.mark.parametrize("fork", ["1", "0"])
def test_modules_in_the_working_directory_do_not_replace_the_nodes(tmp_path, paper_path, fork):
    """Forked nodes (the launcher's preload) and new interpreters (``COVNET_FORK=0``, what a
    restart starts): the run completes and no user module ran."""
    here = _folder_of_user_modules(tmp_path)
    cfg = _config(tmp_path, paper_path, scans=4)
    out = tmp_path / "run"
    p = _up(["up", str(cfg), "--out", str(out), "--no-figures", "--metric", "spectral"], here, fork)
    try:
        rc = p.wait(timeout=150)
    finally:
        p.stop()
    assert rc == 0, p.output()
    assert "user's" not in p.output(), p.output()
    assert json.loads((out / "summary.json").read_text())["completed"] is True
    assert_nothing_left(out)


# a 15 s realtime run: under the slow marker (the suite's time); the restart's new interpreter
# gets the same ProcessSpec environment as COVNET_FORK=0's nodes above
@pytest.mark.slow
def test_a_restarted_sensor_is_covnets_node(tmp_path, paper_path):
    """``restart: on-failure``: the sensor killed mid-run is restarted as a new interpreter in
    the user's folder, and rejoins.  The launcher runs as ``python -P -m covnet`` (as the
    ``covnet`` console script, no working directory on its path: its forked nodes were always
    covnet's), so what is tested is the restart's new interpreter."""
    here = _folder_of_user_modules(tmp_path)
    cfg = _config(tmp_path, paper_path, scans=300, network={"restart": "on-failure"})
    out = tmp_path / "run"
    args = ["up", str(cfg), "--out", str(out), "--realtime", "--speed", "20", "--metric",
            "spectral", "--no-figures"]  # fmt: skip
    # sh -c 'exec "$0" -P "$@"' python -m covnet ARGS: python -P -m covnet ARGS
    p = CovnetProcess(args, cwd=here, prefix=["sh", "-c", 'exec "$0" -P "$@"'])
    try:
        assert p.wait_for("[manager] READY", timeout=60), p.output()
        assert p.wait_for(lambda s: re.search(r"scan ([5-9]|\d\d)/", s) is not None, timeout=30)
        os.kill(json.loads((out / "processes.json").read_text())["S5"], signal.SIGKILL)
        rc = p.wait(timeout=60)
    finally:
        p.stop()
    assert rc == 0, p.output()
    assert "user's" not in p.output(), p.output()
    events = json.loads((out / "summary.json").read_text())["failures"]["spectral"]
    assert [e["event"] for e in events if e["sensor"] == "S5"] == ["failed", "rejoined"], events
    assert_nothing_left(out)


@pytest.mark.parametrize("imported", [False, True])
def test_a_program_calling_covnet_up_from_such_a_folder(tmp_path, paper_path, imported):
    """``covnet.cli.main(["up", ...])`` called by a script in a folder holding a ``sensors.py``
    (the script's folder first on its path): the launcher imported that file for its forked
    nodes, a traceback or the user's module run in it (hunt 15).  Covnet's own are imported;
    a program that imported a ``sensors`` of its own keeps it, and the nodes are new
    interpreters."""
    import subprocess
    import sys

    here = _folder_of_user_modules(tmp_path)
    cfg = _config(tmp_path, paper_path, scans=4)
    out = tmp_path / "run"
    (here / "go.py").write_text(
        ("import sensors\n" if imported else "")
        + "import sys\nfrom covnet.cli.app import main\n"
        + f"rc = main(['up', {str(cfg)!r}, '--out', {str(out)!r}, '--no-figures',"
        + " '--metric', 'spectral'])\n"
        + ("assert sensors.SITES\n" if imported else "")
        + "sys.exit(rc)\n"
    )
    p = subprocess.run([sys.executable, "go.py"], cwd=here, capture_output=True, text=True,
                       timeout=150)  # fmt: skip
    said = p.stdout + p.stderr
    assert p.returncode == 0, said
    assert "Traceback" not in said
    assert said.count("user's sensors.py ran") == (1 if imported else 0), said
    assert json.loads((out / "summary.json").read_text())["completed"] is True
    assert_nothing_left(out)
