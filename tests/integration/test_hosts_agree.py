"""Hosts of one run must run one config (hunt 11): two launchers on 127.0.0.1 given one
``--run`` and router, the sensors' with another ``--seed`` (or a stale copy of the config),
ran one mixed network, both exiting 0, ``run.json`` claiming the manager's config and seed.
Every node's heartbeat now carries its config's identity
(:func:`covnet.processes.node_kit.config_id`), and the manager refuses to start with a node of
another, naming it."""

from __future__ import annotations

import json
import os
import re
import signal
import time
from collections import Counter

import pytest
import yaml
from multiproc import CovnetProcess, assert_nothing_left

from covnet.processes.node_kit import config_id
from covnet.processes.up import free_port

pytestmark = [pytest.mark.integration, pytest.mark.timeout(180)]


def _short(paper_path, tmp_path, name="p.yaml", **over):
    data = yaml.safe_load(paper_path.read_text())
    data.update({"scans": 12, **over})
    data["network"] = {**data.get("network", {}), "ready_timeout_s": 20.0}
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data))
    return path


def test_a_host_of_another_seed_is_refused_by_name(tmp_path, paper_path):
    rc_a, out, rc_b, said_b, a_out = _two_hosts(tmp_path, paper_path, [], ["--seed", "7"])
    assert rc_a == 1, out
    # every node of the other config, each named with its identity (the first one heard alone,
    # often S1, was named before)
    assert "another config" in out and "--seed" in out, out
    named = set(re.findall(r"(S\d+) \([0-9a-f]{16}\)", out))
    assert named == {f"S{i}" for i in range(1, 9)}, out
    info = json.loads((a_out / "run.json").read_text())
    assert info["status"] == "failed" and "another config" in info["ended"]
    assert info["scans_completed"] == {}  # refused before the first scan: nothing mixed
    # the sensors' host does not say the run went well (it exited 0, "stopped" lines only)
    assert rc_b == 1 and "did not end well" in said_b, said_b
    assert_nothing_left(a_out)


def _two_hosts(tmp_path, paper_path, a_extra, b_extra):
    """The manager's host (``--nodes manager,world,recorder``, options ``a_extra``) and a
    sensors' host (``b_extra``) of one run: ``(rc_a, output_a, rc_b, output_b, out_a)``."""
    cfg = _short(paper_path, tmp_path)
    router = f"tcp/127.0.0.1:{free_port()}"
    common = [str(cfg), "--router", router, "--run", f"two{os.getpid()}", "--no-figures"]
    a_out = tmp_path / "a"
    return (*_run_hosts([*common, *a_extra], [*common, *b_extra], tmp_path), a_out)


def _run_hosts(a_args, b_args, tmp_path):
    """``covnet up ARGS --out TMP/a --nodes manager,world,recorder`` (``a_args``) and ``covnet
    up ARGS --out TMP/b --nodes sensors`` (``b_args``) together, until both end:
    ``(rc_a, output_a, rc_b, output_b)``."""
    a_out, b_out = tmp_path / "a", tmp_path / "b"
    mgr = CovnetProcess(["up", *a_args, "--out", str(a_out), "--nodes", "manager,world,recorder"])
    sens = CovnetProcess(["up", *b_args, "--out", str(b_out), "--nodes", "sensors"])
    try:
        rc_a = mgr.wait(timeout=90)
        rc_b = sens.wait(timeout=60)
    finally:
        mgr.stop()
        sens.stop()
    return rc_a, mgr.output(), rc_b, sens.output()


def test_hosts_without_run_meet_where_the_identity_agrees(tmp_path, paper_path):
    """No ``--run``: the manager's host given ``--metric`` and a copy naming ``network.router``,
    the sensors' host none and a copy naming ``network.connect`` (both may differ per host)
    derived two run ids (hunt 14): the hosts never met, both exited 1 after the ready timeout.
    The default run id is now derived from what the config identity holds."""
    router = f"tcp/127.0.0.1:{free_port()}"
    a_cfg = _short(paper_path, tmp_path, "a.yaml", network={"router": router})
    b_cfg = _short(paper_path, tmp_path, "b.yaml", network={"connect": router})
    a_out = tmp_path / "a"
    rc_a, said_a, rc_b, said_b = _run_hosts(
        [str(a_cfg), "--metric", "spectral", "--no-figures"], [str(b_cfg)], tmp_path
    )
    assert (rc_a, rc_b) == (0, 0), (said_a, said_b)
    info = json.loads((a_out / "run.json").read_text())
    assert info["status"] == "completed" and info["run_id"].startswith("paper-"), info
    assert f"run {info['run_id']}:" in said_b, said_b
    assert_nothing_left(a_out)


def test_a_nodes_only_launcher_names_the_endpoint_its_nodes_connect_to(tmp_path, paper_path):
    """``network.connect`` given and the router left at its default ``tcp/127.0.0.1:0``: the
    launcher printed ``-> router tcp/127.0.0.1:<a free port it just invented>`` while its
    sensors connected to ``network.connect`` (hunt 14)."""
    connect = f"tcp/127.0.0.1:{free_port()}"
    cfg = _short(paper_path, tmp_path, "b.yaml", network={"connect": connect})
    p = CovnetProcess(["up", str(cfg), "--out", str(tmp_path / "b"), "--nodes", "sensors"])
    try:
        line = p.wait_for("[launcher] run", timeout=60)
    finally:
        p.stop()
    assert line is not None and line.endswith(f"-> router {connect}"), p.output()


def test_a_host_of_another_speed_is_refused(tmp_path, paper_path):
    """Hosts of one realtime run given different ``--speed``s ran one network, the sensors
    emulating their links' delays at their own speed and the manager timing the scans at its
    own: 33 m of RMSE against 7, ``completed`` (hunt 12).  The clock options are part of every
    node's config identity."""
    rc_a, out, rc_b, said_b, a_out = _two_hosts(
        tmp_path, paper_path, ["--realtime", "--speed", "20"], ["--realtime", "--speed", "10"]
    )
    assert rc_a == 1 and "another config" in out and "--speed" in out, out
    assert json.loads((a_out / "run.json").read_text())["scans_completed"] == {}
    assert rc_b == 1, said_b
    assert_nothing_left(a_out)


def test_a_sensor_run_twice_is_named(tmp_path, paper_path):
    """S3 started on two hosts (``--nodes sensors`` on one, ``--nodes S3`` on another): the run
    completed and only ``network.json``'s ``duplicate`` count said anything (hunt 11).  The
    manager names the sensor whose measurements came twice."""
    cfg = _short(paper_path, tmp_path)
    router = f"tcp/127.0.0.1:{free_port()}"
    common = [str(cfg), "--router", router, "--run", f"twice{os.getpid()}", "--no-figures"]
    a_out, b_out = tmp_path / "a", tmp_path / "b"
    # the second S3 first: up before the run starts (the manager waits for every token)
    again = CovnetProcess(["up", *common, "--out", str(b_out), "--nodes", "S3"])
    try:
        assert again.wait_for("[launcher]", timeout=30), again.output()
    except BaseException:
        again.stop()
        raise
    mgr = CovnetProcess(["up", *common, "--out", str(a_out), "--metric", "spectral"])
    try:
        rc_a = mgr.wait(timeout=90)
        again.wait(timeout=60)
    finally:
        mgr.stop()
        again.stop()
    said = mgr.output()
    dup = json.loads((a_out / "network.json").read_text())["rejected"].get("duplicate", 0)
    assert rc_a == 0 and dup > 0, said
    assert f"note: {dup} of S3's measurements came twice" in said, said
    assert "run by two processes at once" in said


def test_config_id_holds_the_clock_options(tmp_path, paper_path):
    from covnet import kinds
    from covnet.processes import node_kit

    _, cfg = kinds.load(_short(paper_path, tmp_path, "c.yaml"))
    try:
        ids = []
        for realtime, speed in [(False, 1.0), (False, 20.0), (True, 1.0), (True, 20.0)]:
            node_kit.set_run_clock(realtime, speed)
            ids.append(config_id(cfg))
    finally:
        node_kit.set_run_clock(False, 1.0)
    assert ids[0] == ids[1]  # lockstep: the speed paces nothing
    assert len(set(ids[1:])) == 3


def _manager_killed_mid_run(
    tmp_path, paper_path, host_a: str, host_b: str, realtime: bool = True, **over
):
    """Two launchers of a run (``--nodes host_a`` and ``--nodes host_b``; realtime unless
    ``realtime`` is false: peer mode); the manager SIGKILLed once the run goes: ``(rc_a, rc_b,
    out_a, out_b, output_a, output_b)``."""
    cfg = _short(paper_path, tmp_path, **{"scans": 400, **over})
    router = f"tcp/127.0.0.1:{free_port()}"
    common = [str(cfg), "--router", router, "--run", f"die{os.getpid()}", "--no-figures"]
    common += ["--realtime", "--speed", "20"] if realtime else []
    a_out, b_out = tmp_path / "a", tmp_path / "b"
    mgr = CovnetProcess(["up", *common, "--out", str(a_out), "--nodes", host_a])
    sens = CovnetProcess(["up", *common, "--out", str(b_out), "--nodes", host_b])
    try:
        assert mgr.wait_for("[manager] READY", timeout=60), mgr.output() + sens.output()
        assert mgr.wait_for(lambda s: "[status]" in s, timeout=30), mgr.output()
        pid = json.loads((a_out / "processes.json").read_text())["manager"]
        os.kill(pid, signal.SIGKILL)
        rc_b = sens.wait(timeout=60)
        rc_a = mgr.wait(timeout=60)
    finally:
        mgr.stop()
        sens.stop()
    return rc_a, rc_b, a_out, b_out, mgr.output(), sens.output()


def test_a_sensors_host_says_so_when_the_managers_host_dies(tmp_path, paper_path):
    """The manager's host killed mid-run: the sensors' host exited 0 with the lines of a
    completed run, about 3 s later; it now exits 1 saying the run did not end well."""
    _, rc_b, _, _, _, said = _manager_killed_mid_run(
        tmp_path, paper_path, "manager,world,recorder", "sensors"
    )
    assert rc_b == 1 and "did not end well" in said, said


def test_the_world_and_peer_nodes_say_so_too(tmp_path, paper_path):
    """The world on the sensors' host (and, in peer mode, the peer nodes) exited 0 with the
    lines of a completed run when the manager's (the monitor's) host died mid-run; each now
    exits with ``EXIT_RUN_FAILED`` saying the run did not end well."""
    (tmp_path / "central").mkdir()
    (tmp_path / "peer").mkdir()
    _, rc_b, _, _, _, said = _manager_killed_mid_run(
        tmp_path / "central", paper_path, "manager,recorder", "sensors,world"
    )
    assert rc_b == 1 and "the world stopped with it" in said, said
    _, rc_b, _, _, _, said = _manager_killed_mid_run(
        tmp_path / "peer",
        paper_path,
        "manager,recorder",
        "sensors,world",
        realtime=False,
        scans=3000,
        fusion={"mode": "peer", "peer": {"graph": "ring"}},
    )
    assert rc_b == 1 and "this peer node stopped with it" in said, said
    assert "the world stopped with it" in said, said


def test_restartable_nodes_are_not_restarted_into_a_run_that_is_over(tmp_path, paper_path):
    """``network.restart: on-failure`` on a sensors-only host whose manager's host died: the
    sensors left saying the run did not end well (exit 1), were restarted, waited for a
    manager that never came, failed and were restarted again: the host never ended.  A node
    that leaves for that (``EXIT_RUN_FAILED``) is not restarted, and its launcher ends."""
    net = {"ready_timeout_s": 20.0, "restart": "on-failure"}
    t0 = time.monotonic()
    _, rc_b, _, b_out, _, said = _manager_killed_mid_run(
        tmp_path, paper_path, "manager,recorder", "sensors,world", network=net
    )
    assert rc_b == 1 and "did not end well" in said, said
    assert time.monotonic() - t0 < 120
    assert "restart" not in said.lower(), said
    assert_nothing_left(b_out)


def test_a_sensors_host_that_finds_no_run_ends_restart_or_not(tmp_path, paper_path):
    """``restart: on-failure`` on a sensors-only host with no router at ``--router`` (or no
    manager of its run): each sensor failed to join, exit 1, and was restarted, every half
    minute without end (hunt 12).  A node that finds no run to join exits ``EXIT_NO_RUN``, is
    not restarted, and the host ends with exit 1 once ``ready_timeout_s`` has passed."""
    cfg = _short(paper_path, tmp_path, network={"restart": "on-failure"})
    data = yaml.safe_load(cfg.read_text())
    data["network"]["ready_timeout_s"] = 2.0
    cfg.write_text(yaml.safe_dump(data))
    router = f"tcp/127.0.0.1:{free_port()}"  # nothing listens there
    out = tmp_path / "b"
    sens = CovnetProcess(
        ["up", str(cfg), "--router", router, "--run", f"none{os.getpid()}", "--out", str(out),
         "--nodes", "S1,S2"]
    )  # fmt: skip
    try:
        rc = sens.wait(timeout=60)
    finally:
        sens.stop()
    said = sens.output()
    assert rc == 1, said
    assert said.count("cannot open a zenoh client session") == 2, said  # once each, no restart
    assert_nothing_left(out)


@pytest.mark.parametrize(
    ("node", "fusion"), [("recorder", "central"), ("world", "central"), ("recorder", "peer")]
)
def test_a_world_or_recorder_of_another_host_that_dies_is_a_run_not_complete(
    tmp_path, paper_path, node, fusion
):
    """The recorder (or the world) on the sensors' host killed mid-run: the manager's host
    said `completed` and exited 0 (its launcher watches only its own processes), the recording
    ending hundreds of scans before the run; the other host exited 1 without a word (hunt 12).
    The manager notes the world and recorder down at the end, the manager's host says which
    after which scan and exits 1 (`run.json` failed, `lost`), and the other host names its
    failed node."""
    cfg = _short(paper_path, tmp_path, scans=100)
    router = f"tcp/127.0.0.1:{free_port()}"
    common = [str(cfg), "--router", router, "--run", f"rec{os.getpid()}", "--no-figures"]
    common += ["--metric", "spectral", "--fusion", fusion]
    # 5 s from the first scan, whose [status] line comes at once (peer mode runs in lockstep,
    # about 20 scans a second here, slower under load: longer)
    common += ["--realtime", "--speed", "20"] if fusion == "central" else []
    a_out, b_out = tmp_path / "a", tmp_path / "b"
    here = "manager,world" if node == "recorder" else "manager,recorder"
    mgr = CovnetProcess(["up", *common, "--out", str(a_out), "--nodes", here])
    sens = CovnetProcess(["up", *common, "--out", str(b_out), "--nodes", f"sensors,{node}"])
    try:
        assert mgr.wait_for("[manager] READY", timeout=60), mgr.output() + sens.output()
        assert mgr.wait_for(lambda s: "[status]" in s, timeout=30), mgr.output()
        pid = json.loads((b_out / "processes.json").read_text())[node]
        os.kill(pid, signal.SIGKILL)
        rc_a = mgr.wait(timeout=90)
        rc_b = sens.wait(timeout=60)
    finally:
        mgr.stop()
        sens.stop()
    said_a, said_b = mgr.output(), sens.output()
    assert rc_a == 1, said_a
    assert re.search(rf"the {node}, on another host, was gone after scan \d+", said_a), said_a
    info = json.loads((a_out / "run.json").read_text())
    assert info["status"] == "failed" and info["lost"][0]["node"] == node, info
    assert info["membership"][node]["failed"] == 1
    assert rc_b == 1 and f"[launcher] {node} failed (exit status -9)" in said_b, said_b
    assert_nothing_left(a_out)


def test_config_id_ignores_only_the_per_host_keys(tmp_path, paper_path):
    """The hosts' endpoints and security files may differ; the rest may not."""
    from covnet import kinds

    def cid(**over):
        _, cfg = kinds.load(_short(paper_path, tmp_path, "c.yaml", **over))
        return config_id(cfg)

    base = cid()
    assert cid(network={"router": "tcp/127.0.0.1:7447", "ready_timeout_s": 20.0}) == base
    assert cid(network={"connect": "tcp/127.0.0.1:7447", "ready_timeout_s": 20.0}) == base
    assert cid(seed=7) != base
    assert cid(allocation={"metrics": ["svd"]}) == base  # the manager's episodes, its own
    assert cid(network={"heartbeat_s": 0.1, "ready_timeout_s": 20.0}) != base


def test_a_manager_host_without_the_recorder_does_not_say_nothing_was_recorded(
    tmp_path, paper_path
):
    """The recorder on the sensors' host and the manager killed mid-run: the manager's host
    said "nothing was recorded" and wrote ``scans_completed: 0`` after dozens of scans, while
    the recording on the other host held them (hunt 11)."""
    rc_a, _, a_out, b_out, said, _ = _manager_killed_mid_run(
        tmp_path, paper_path, "manager,world", "sensors,recorder"
    )
    assert rc_a == 1 and "recorder ran on another host" in said, said
    assert "nothing was recorded" not in said
    info = json.loads((a_out / "run.json").read_text())
    assert info["status"] == "failed" and info.get("scans_completed") != 0, info
    assert (b_out / "recording.mcap").is_file()


def _monotonic_offset_works() -> bool:
    import shutil
    import subprocess

    if shutil.which("unshare") is None:
        return False
    r = subprocess.run(["unshare", "--time", "--monotonic", "5", "true"], capture_output=True)
    return r.returncode == 0


@pytest.mark.skipif(not _monotonic_offset_works(), reason="no time namespaces (unshare --time)")
def test_latency_is_not_taken_across_clocks(tmp_path, paper_path):
    """The sensors' host an hour younger (its CLOCK_MONOTONIC offset by a time namespace, as
    two hosts' uptimes differ): ``network.json``'s one-way measurement latency subtracted one
    clock from the other (a p50 of -3 599 999 ms, hunt 11).  Each heartbeat names its host and
    clock (``node_kit.host_id``), and a latency is taken only between nodes of one clock; the
    others are counted.  The results are ``covnet run``'s (no decision reads those clocks)."""
    from covnet.cli.app import main as covnet_main

    cfg = _short(paper_path, tmp_path)
    ref = tmp_path / "ref"
    assert covnet_main(["run", str(cfg), "--out", str(ref), "--no-figures"]) == 0
    router = f"tcp/127.0.0.1:{free_port()}"
    common = [str(cfg), "--router", router, "--run", f"clk{os.getpid()}", "--no-figures"]
    a_out, b_out = tmp_path / "a", tmp_path / "b"
    mgr = CovnetProcess(["up", *common, "--out", str(a_out), "--nodes", "manager,world,recorder"])
    sens = CovnetProcess(
        ["up", *common, "--out", str(b_out), "--nodes", "sensors"],
        prefix=["unshare", "--time", "--monotonic", "3600"],
    )
    try:
        assert mgr.wait(timeout=120) == 0, mgr.output() + sens.output()
        assert sens.wait(timeout=60) == 0, sens.output()
    finally:
        mgr.stop()
        sens.stop()
    net = json.loads((a_out / "network.json").read_text())
    assert net["measurement_latency"]["n"] == 0, net["measurement_latency"]
    assert net["measurement_latency_other_clocks"] > 0
    # the recording (on the manager's host): the sensors' host's stamps are not the recording's
    # publish_time (an hour after the receipt: MCAP's "not known" is the receive time); their
    # payloads keep them; the manager's own messages keep theirs
    from covnet.runs.recording import read_recording
    from covnet.wire import messages as wire

    seen = Counter()
    for r in read_recording(a_out / "recording.mcap"):
        what = r.key.split("/")[2]
        if what not in ("sensor", "cmd"):
            continue
        seen[what] += 1
        stamp = wire.decode(r.payload).t_sent_ns
        if what == "sensor":  # a measurement of the other host
            assert r.t_sent_ns == r.t_recv_ns and stamp - r.t_recv_ns > 3000e9, r.key
        else:
            assert r.t_sent_ns == stamp and 0 <= r.t_recv_ns - stamp < 60e9, r.key
    assert seen["sensor"] > 10 and seen["cmd"] > 10, seen
    got = json.loads((a_out / "summary.json").read_text())["metrics"]
    want = json.loads((ref / "summary.json").read_text())["metrics"]
    for m in want:
        assert got[m]["subsets"] == want[m]["subsets"] and got[m]["P_diag"] == want[m]["P_diag"]


def test_a_peer_host_of_another_seed_is_refused_too(tmp_path, paper_path):
    """Peer mode: the observer, not the manager's loop, waits for the nodes; it refuses a node
    of another config as the manager does (the run fails, named, before anything is
    reported; the nodes leave on its failed end)."""
    cfg = _short(paper_path, tmp_path)
    router = f"tcp/127.0.0.1:{free_port()}"
    common = [str(cfg), "--router", router, "--run", f"peer{os.getpid()}", "--no-figures",
              "--fusion", "peer"]  # fmt: skip
    a_out, b_out = tmp_path / "a", tmp_path / "b"
    mgr = CovnetProcess(["up", *common, "--out", str(a_out), "--nodes", "manager,world,recorder"])
    sens = CovnetProcess(["up", *common, "--out", str(b_out), "--nodes", "sensors", "--seed", "7"])
    try:
        rc_a = mgr.wait(timeout=90)
        t0 = time.monotonic()
        sens.wait(timeout=60)
        # the peer nodes leave on the failed end (they waited ready_timeout_s, 20 s, for the
        # monitor that had gone)
        assert time.monotonic() - t0 < 15, sens.output()
    finally:
        mgr.stop()
        sens.stop()
    out = mgr.output()
    assert rc_a == 1 and "another config" in out, out
    assert set(re.findall(r"(S\d+) \([0-9a-f]{16}\)", out)) == {f"S{i}" for i in range(1, 9)}
    info = json.loads((a_out / "run.json").read_text())
    assert info["status"] == "failed" and "another config" in info["ended"]
