"""``covnet up --netns``: every sensor in its own network namespace, joined to the manager's by an
emulated link (covnet.processes.netns_launch).  A 20 ms uplink shows as ~20 ms one-way measurement
latency; with ideal links the run equals ``covnet run``; Ctrl-C and a crashed manager still
remove every namespace, link and forwarder; bad combinations exit 2.  The runs are skipped, with
the reason, where namespaces or TUN devices cannot be made (not root, no iproute2, no
/dev/net/tun)."""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from multiproc import CovnetProcess, assert_nothing_left, pid_alive

from covnet.cli.app import main as covnet_main
from covnet.core.delay import DelayDist, LinkSpec
from covnet.processes.launch import ProcessSpec
from covnet.processes.netem.detect import run_ip
from covnet.processes.netns_launch import NetnsTopology, SensorLink, scaled, unsupported_reason
from covnet.runs.rundir import load_arrays

pytestmark = [pytest.mark.integration, pytest.mark.timeout(240)]


def _namespaces_of(pid: int) -> list[str]:
    """The namespaces ``covnet up --netns`` with launcher ``pid`` made (``cvn<pid>m``,
    ``cvn<pid>s<j>``) that still exist."""
    names = [line.split()[0] for line in run_ip("netns", "list").stdout.splitlines() if line]
    return [n for n in names if n == f"cvn{pid}m" or n.startswith(f"cvn{pid}s")]


def _devices_of(pid: int) -> list[str]:
    """TUN/veth devices of that launcher's links still in the root namespace."""
    tag = f"{pid % 100000}x"
    out = run_ip("-o", "link", "show").stdout
    return [w for w in out.split() if w.startswith(("cvt" + tag, "cvv" + tag))]


@pytest.fixture()
def netns_run():
    """Start ``covnet up ... --netns`` as a child; afterwards stop it and delete whatever it
    left (so a failing test leaves nothing either)."""
    reason = unsupported_reason()
    if reason is not None:
        pytest.skip(reason)
    probe = f"cvnprobe{os.getpid()}"
    r = run_ip("netns", "add", probe)
    if r.returncode != 0:
        pytest.skip(f"cannot create a network namespace: {r.stderr.strip()}")
    run_ip("netns", "del", probe)
    started: list[CovnetProcess] = []

    def start(args: list[str]) -> CovnetProcess:
        p = CovnetProcess(["up", *args, "--netns", "--no-figures"])
        started.append(p)
        return p

    yield start
    for p in started:
        p.stop()
        for ns in _namespaces_of(p.proc.pid):
            run_ip("netns", "del", ns)


def assert_all_removed(p: CovnetProcess, out: Path) -> None:
    """No node process, forwarder, namespace or link device of this run is left."""
    assert_nothing_left(out)
    # run.json when the manager wrote one, else netns.json (a manager killed early)
    where = out / "run.json" if (out / "run.json").is_file() else out / "netns.json"
    topo = json.loads(where.read_text())["netns"]
    fw = [lk["forwarder_pid"] for lk in topo["links"].values() if lk["forwarder_pid"]]
    deadline = time.monotonic() + 5
    while any(pid_alive(x) for x in fw) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not [x for x in fw if pid_alive(x)], "forwarders left running"
    assert _namespaces_of(p.proc.pid) == []
    assert _devices_of(p.proc.pid) == []


def _config(tmp_path: Path, paper_path: Path, latency: dict | None, scans: int = 30) -> Path:
    data = yaml.safe_load(paper_path.read_text())
    data["scans"] = scans
    if latency is not None:
        data["network"] = {"latency": latency}
    path = tmp_path / "netns.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def _netns_inode(pid: int) -> int:
    return os.stat(f"/proc/{pid}/ns/net").st_ino


def test_uplink_delay_on_the_real_path(netns_run, tmp_path, paper_path):
    # 100 ms of scenario time at --speed 5: 20 ms on the wire, well inside the 160 ms deadline
    cfg = _config(tmp_path, paper_path, {"uplink": {"delay": {"kind": "constant", "value_s": 0.1}}})
    out = tmp_path / "up"
    p = netns_run(
        [str(cfg), "--out", str(out), "--realtime", "--speed", "5", "--metric", "spectral"]
    )
    assert p.wait_for("[manager] READY", timeout=120), p.output()
    # processes.json holds the python processes themselves, each in its namespace
    pids = json.loads((out / "processes.json").read_text())
    inodes = {}
    for name, pid in pids.items():
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        assert b"python" in os.path.basename(cmdline[0]) and b"-m" in cmdline, (name, cmdline)
        inodes[name] = _netns_inode(pid)
    assert inodes["world"] == inodes["manager"] == inodes["recorder"] != _netns_inode(os.getpid())
    sensor_ns = [inodes[s] for s in pids if s.startswith("S")]
    assert len(set(sensor_ns)) == 8 and inodes["manager"] not in sensor_ns
    rc = p.wait(timeout=180)
    assert rc == 0, p.output()
    assert_all_removed(p, out)
    lat = json.loads((out / "network.json").read_text())["measurement_latency"]
    # the manager stamps send -> receive on the machine's monotonic clock: 20 ms plus zenoh
    # and the forwarder's lateness (docs/netem.md: ~0.2 ms typical, a few ms in the tail)
    assert lat["n"] > 50
    assert 20.0 <= lat["p50_ms"] <= 30.0, lat
    topo = json.loads((out / "run.json").read_text())["netns"]
    assert topo["speed"] == 5.0
    s3 = topo["links"]["S3"]
    assert s3["wire_uplink"]["delay"]["value_s"] == pytest.approx(0.02)
    assert s3["sensor_addr"] == "10.77.0.9" and s3["manager_addr"] == "10.77.0.10"
    if s3["mode"] == "userspace":
        up, down = s3["counters"]["uplink"], s3["counters"]["downlink"]
        assert up["received"] == up["forwarded"] > 0 and up["lost"] == 0
        assert down["forwarded"] > 0


def test_ideal_links_in_lockstep_equal_covnet_run(netns_run, tmp_path, paper_path):
    cfg = _config(tmp_path, paper_path, None)
    ref, out = tmp_path / "ref", tmp_path / "up"
    assert covnet_main(["run", str(cfg), "--out", str(ref), "--no-figures"]) == 0
    p = netns_run([str(cfg), "--out", str(out)])
    rc = p.wait(timeout=200)
    assert rc == 0, p.output()
    assert_all_removed(p, out)
    a = json.loads((ref / "summary.json").read_text())
    b = json.loads((out / "summary.json").read_text())
    x, y = load_arrays(ref / "arrays.npz"), load_arrays(out / "arrays.npz")
    for m in a["metrics"]:
        assert b["metrics"][m]["subsets"] == a["metrics"][m]["subsets"]
        for key in (f"x_est.{m}", f"P_post.{m}"):
            np.testing.assert_allclose(y[key], x[key], rtol=0, atol=1e-12)


@pytest.mark.parametrize("how", ["ctrl-c", "manager-killed"])
def test_everything_removed_on_interrupt_and_crash(netns_run, tmp_path, paper_path, how):
    cfg = _config(tmp_path, paper_path, None, scans=200)
    out = tmp_path / "up"
    p = netns_run([str(cfg), "--out", str(out), "--realtime", "--metric", "spectral"])
    assert p.wait_for("[status]", timeout=120), p.output()
    assert _namespaces_of(p.proc.pid), "no namespaces while running"
    if how == "ctrl-c":
        os.kill(p.proc.pid, signal.SIGINT)
        want = 130
    else:
        os.kill(json.loads((out / "processes.json").read_text())["manager"], signal.SIGKILL)
        want = 1
    assert p.wait(timeout=60) == want, p.output()
    assert_all_removed(p, out)


def test_bad_combinations_exit_2(tmp_path, paper_path, capsys, monkeypatch):
    cfg = str(paper_path)
    assert covnet_main(["up", cfg, "--netns", "--nodes", "manager", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "--netns" in err and "--nodes" in err and "Traceback" not in err
    assert covnet_main(["up", cfg, "--netns", "--router", "tcp/127.0.0.1:7447"]) == 2
    assert "--router" in capsys.readouterr().err
    monkeypatch.setattr("covnet.processes.netns_launch.os.geteuid", lambda: 1000)
    assert covnet_main(["up", cfg, "--netns", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert "root" in err and "--realtime" in err and "Traceback" not in err


def test_link_specs_scale_with_speed_and_processes_are_placed():
    spec = LinkSpec(DelayDist("exponential", offset_s=0.1, mean_s=0.5), jitter_s=0.05, loss=0.1)
    fast = scaled(spec, 5.0)
    assert fast.delay.offset_s == pytest.approx(0.02) and fast.delay.mean_s == pytest.approx(0.1)
    assert fast.jitter_s == pytest.approx(0.01) and fast.loss == 0.1
    assert scaled(spec, 1.0) is spec
    ideal = LinkSpec()
    topo = NetnsTopology("cvn1m", 7447, "tcp/0.0.0.0:7447", "tcp/127.0.0.1:7447")
    topo.links["S1"] = SensorLink("S1", 0, "cvn1s1", "10.77.0.1", "10.77.0.2", *[ideal] * 4)
    specs = [
        ProcessSpec("manager", ["py", "-m", "manager", "--listen", "tcp/127.0.0.1:1"]),
        ProcessSpec("world", ["py", "-m", "world", "--connect", "tcp/127.0.0.1:1"]),
        ProcessSpec("S1", ["py", "-m", "sensors", "--connect", "tcp/127.0.0.1:1"], restart=True),
    ]
    got = {sp.name: sp for sp in topo.apply(specs)}
    assert got["manager"].argv == ["ip", "netns", "exec", "cvn1m", "py", "-m", "manager",
                                   "--listen", "tcp/0.0.0.0:7447", "--no-app-latency"]  # fmt: skip
    assert got["world"].argv[3:4] == ["cvn1m"] and "tcp/127.0.0.1:7447" in got["world"].argv
    assert got["S1"].argv[3] == "cvn1s1" and "tcp/10.77.0.2:7447" in got["S1"].argv
    assert got["S1"].restart and got["S1"].argv[-1] == "--no-app-latency"
