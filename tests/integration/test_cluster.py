"""``--cluster`` (issue 18): a real ``dask scheduler`` and two ``dask worker`` processes on
127.0.0.1 (free ports, each in its own session, stopped by PID: nothing is left running), and
``covnet sweep``, ``compare`` and ``mc`` (both kinds) on them give the local pool's results bit
for bit."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import pytest
import yaml
from multiproc import REPO, CovnetProcess, run_to_end

pytest.importorskip("distributed")

from covnet.batches.cluster import LocalCluster  # noqa: E402

pytestmark = [pytest.mark.integration]


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.fixture(scope="module")
def cluster():
    with LocalCluster(workers=2, threads=1) as c:
        pids = list(c.pids)
        assert len(pids) == 3 and all(_alive(p) for p in pids)
        yield c
    deadline = time.monotonic() + 10
    while any(_alive(p) for p in pids) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not [p for p in pids if _alive(p)], "dask processes left running"


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("cfg")
    lat = yaml.safe_load((REPO / "configs" / "latency.yaml").read_text())
    lat["scans"] = 25
    lat["sweep"] = {
        "delay_ms": [0, 350],
        "loss": [0.0, 0.2],
        "modes": ["central", "ci"],
        "account_for_loss": [False],
        "seeds": 2,
    }
    (d / "sweep.yaml").write_text(yaml.safe_dump(lat))
    paper = yaml.safe_load((REPO / "configs" / "paper.yaml").read_text())
    paper["scans"] = 25
    (d / "paper.yaml").write_text(yaml.safe_dump(paper))
    mob = yaml.safe_load((REPO / "configs" / "mobile.yaml").read_text())
    mob["scans"] = 15
    (d / "mobile.yaml").write_text(yaml.safe_dump(mob))
    pas = yaml.safe_load((REPO / "configs" / "passive.yaml").read_text())
    pas["montecarlo"].update(
        {"trials": 3, "formations": ["cross"], "spacings_km": [1.0], "sigmas_mrad": [3.0]}
    )
    (d / "passive.yaml").write_text(yaml.safe_dump(pas))
    return {k: d / f"{k}.yaml" for k in ("sweep", "paper", "mobile", "passive")}


def _strip(obj):
    """Without the wall-clock fields (a passive cell's median time, a run's wall time)."""
    wall = {"median_time_s", "wall_s", "created_utc", "decision_time_s", "workers", "cluster"}
    if isinstance(obj, dict):
        return {k: _strip(v) for k, v in obj.items() if k not in wall}
    if isinstance(obj, list):
        return [_strip(v) for v in obj]
    return obj


CASES = {
    "sweep": (["sweep", "{sweep}", "--no-figures"], "sweep.json", False),
    "compare": (
        ["compare", "{paper}", "--runs", "2", "--modes", "central,ci,peer-info", "--no-figures"],
        "compare.json",
        False,
    ),
    "mc-mobile": (["mc", "{mobile}", "--trials", "2"], "montecarlo.json", False),
    "mc-passive": (["mc", "{passive}"], "results.json", True),
}
DEFAULT_CASES = ("sweep", "mc-passive")
"""Run by default (the two quickest, two kinds); ``-m slow`` runs the rest too."""


@pytest.mark.timeout(600)
# two of the batch commands by default, the others under the slow marker (the suite's time)
@pytest.mark.parametrize(
    "case",
    [c if c in DEFAULT_CASES else pytest.param(c, marks=pytest.mark.slow) for c in sorted(CASES)],
)
def test_a_cluster_gives_the_local_results_bit_for_bit(case, cluster, small, tmp_path):
    argv, table, wall = CASES[case]
    args = [a.format(**{k: str(v) for k, v in small.items()}) for a in argv]
    run_to_end([*args, "--out", str(tmp_path / "local"), "--workers", "2"])
    text = run_to_end([*args, "--out", str(tmp_path / "dask"), "--cluster", cluster.address])
    assert f"on {cluster.address}" in text  # the progress line says where
    local = tmp_path / "local" / table
    dask = tmp_path / "dask" / table
    if wall:  # the passive table holds per-scan wall times
        assert _strip(json.loads(local.read_text())) == _strip(json.loads(dask.read_text()))
    else:
        assert local.read_bytes() == dask.read_bytes()
    info = json.loads((tmp_path / "dask" / "run.json").read_text())
    assert info["backend"] == "dask" and info["workers"] == 2
    if case == "mc-passive":  # the cluster's 2 workers, not the local pool's 1 (one cell)
        doc = json.loads(dask.read_text())
        assert (doc["workers"], doc["cluster"]) == (2, cluster.address), doc
        md = (tmp_path / "dask" / "results.md").read_text()
        assert f"on the Dask cluster {cluster.address} (2 workers)" in md, md
        assert "on the Dask cluster" not in (tmp_path / "local" / "results.md").read_text()
    # and the trials themselves, file by file
    loc = sorted((tmp_path / "local" / "trials").rglob("*.json"))
    das = sorted((tmp_path / "dask" / "trials").rglob("*.json"))
    assert [p.relative_to(tmp_path / "local") for p in loc] == [
        p.relative_to(tmp_path / "dask") for p in das
    ]
    if not wall and case != "mc-mobile":  # (a mobile seed's record holds its decision times)
        for a, b in zip(loc, das, strict=True):
            assert a.read_bytes() == b.read_bytes(), a


def test_an_unreachable_scheduler_is_a_usage_error(small, tmp_path):
    import socket

    with socket.socket() as s:  # a free port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    p = CovnetProcess(
        ["sweep", str(small["sweep"]), "--out", str(tmp_path / "x"), "--cluster",
         f"tcp://127.0.0.1:{port}"],
        prefix=None,
    )  # fmt: skip
    env_timeout = float(os.environ.get("COVNET_TEST_TIMEOUT", "60"))
    try:
        rc = p.wait(timeout=env_timeout)
    finally:
        p.stop()
    assert rc == 2, p.output()
    assert "cannot reach a Dask scheduler" in p.output()
    assert "Traceback" not in p.output()
    assert not (tmp_path / "x").exists()  # refused before anything starts


@pytest.mark.parametrize("address", ["127.0.0.1:8786", "tcp://127.0.0.1", "tcp://:8786"])
def test_a_malformed_scheduler_address_is_refused_at_once(small, tmp_path, capsys, address):
    from covnet.cli.app import main

    with pytest.raises(SystemExit) as exc:
        main(["sweep", str(small["sweep"]), "--out", str(tmp_path / "x"), "--cluster", address])
    assert exc.value.code == 2
    assert "expected a Dask scheduler address like tcp://" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_a_port_where_no_scheduler_answers_is_refused_in_bounded_time(
    small, tmp_path, capsys, monkeypatch
):
    """A mistyped port where something else listens (here a TCP server that accepts and never
    says a word, as a web server or a zenoh router does to Dask's handshake): Dask's client
    waited without end (600 s seen) and the batch directory was already made.  Now refused
    within the connect timeout, exit 2, nothing made."""
    import socket
    import threading

    from covnet.batches import cluster as cl
    from covnet.cli.app import main

    monkeypatch.setattr(cl, "CONNECT_TIMEOUT_S", 2.0)
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(4)
    held: list[socket.socket] = []
    stop = threading.Event()

    def accept() -> None:
        server.settimeout(0.2)
        while not stop.is_set():
            try:
                held.append(server.accept()[0])  # kept open, never written to
            except OSError:
                continue

    t = threading.Thread(target=accept, daemon=True)
    t.start()
    try:
        address = f"tcp://127.0.0.1:{server.getsockname()[1]}"
        t0 = time.monotonic()
        rc = main(
            ["sweep", str(small["sweep"]), "--out", str(tmp_path / "x"), "--cluster", address]
        )
        took = time.monotonic() - t0
    finally:
        stop.set()
        t.join()
        for c in held:
            c.close()
        server.close()
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "nothing answered as a Dask scheduler within 2 s" in err, err
    assert took < 30, took
    assert not (tmp_path / "x").exists()


def test_a_scheduler_answers(cluster):
    from covnet.batches.cluster import scheduler_answers

    assert scheduler_answers(cluster.address, 10.0) is None


def test_the_api_sweep_on_a_cluster_gives_the_local_rows(cluster, small):
    """The README's ``api.sweep(..., cluster="tcp://host:8786")`` (no test followed it): the
    same rows as on the local cores."""
    from covnet.cli import api

    local = api.sweep(small["sweep"], seeds=2, workers=2)
    remote = api.sweep(small["sweep"], seeds=2, cluster=cluster.address)
    assert remote.rows == local.rows and len(remote.rows) == 8


@pytest.mark.slow  # ~20 s: Dask's client tries to reconnect for 15 s before it closes
@pytest.mark.timeout(180)
def test_a_scheduler_that_goes_away_fails_the_unfinished_tasks_in_bounded_time():
    """The scheduler killed mid-batch: the batch waited for ever (one future stayed pending:
    Dask's as_completed lost it when fetching its result failed), or ended in a traceback.
    Now the finished tasks come back, every unfinished one is a ClusterLost failure, within
    Dask's reconnection time."""
    from covnet.batches.cluster import DaskRunner
    from covnet.errors import ClusterLost

    with LocalCluster(workers=1, threads=1) as c:
        runner = DaskRunner(c.address)
        try:
            out = []
            t0 = None
            for i, ok, value in runner.imap(time.sleep, [0.0, 0.0, 60.0, 60.0, 60.0]):
                out.append((i, ok, value))
                if sum(ok for _, ok, _ in out) == 2 and t0 is None:
                    c.procs[0].kill()  # the scheduler
                    t0 = time.monotonic()
            elapsed = time.monotonic() - t0
        finally:
            runner.close()
    assert sorted(i for i, ok, _ in out if ok) == [0, 1]
    lost = {i: v for i, ok, v in out if not ok}
    assert sorted(lost) == [2, 3, 4] and all(isinstance(v, ClusterLost) for v in lost.values())
    assert "went away" in str(lost[2])
    assert elapsed < 60, elapsed
