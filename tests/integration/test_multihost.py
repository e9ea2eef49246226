"""Two hosts on one machine: the manager (with world and recorder) in one network namespace,
the sensors in another, joined by a veth pair; the sensors reach the manager's router only over
that link.  The run equals ``covnet run``.  Skipped, with the reason, where namespaces cannot be
made (not root, no iproute2, no CAP_NET_ADMIN)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import pytest
import yaml
from multiproc import CovnetProcess

from covnet.cli.app import main as covnet_main

pytestmark = [pytest.mark.integration, pytest.mark.timeout(240)]

SUBNET = "10.251.{}.{}"


def _ip(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=20)


@pytest.fixture()
def two_hosts():
    if shutil.which("ip") is None:
        pytest.skip("iproute2 ('ip') is not installed")
    if os.geteuid() != 0:
        pytest.skip("creating network namespaces needs root")
    tag = f"{os.getpid() % 100000}"
    ns_a, ns_b = f"cvn{tag}a", f"cvn{tag}b"
    veth_a, veth_b = f"cv{tag}a", f"cv{tag}b"
    octet = os.getpid() % 250
    addr_a, addr_b = SUBNET.format(octet, 1), SUBNET.format(octet, 2)
    made: list[str] = []
    try:
        for ns in (ns_a, ns_b):
            r = _ip("netns", "add", ns)
            if r.returncode != 0:
                pytest.skip(f"cannot create a network namespace: {r.stderr.strip()}")
            made.append(ns)
        steps = [
            ("link", "add", veth_a, "type", "veth", "peer", "name", veth_b),
            ("link", "set", veth_a, "netns", ns_a),
            ("link", "set", veth_b, "netns", ns_b),
            ("-n", ns_a, "addr", "add", f"{addr_a}/30", "dev", veth_a),
            ("-n", ns_b, "addr", "add", f"{addr_b}/30", "dev", veth_b),
            ("-n", ns_a, "link", "set", veth_a, "up"),
            ("-n", ns_b, "link", "set", veth_b, "up"),
            ("-n", ns_a, "link", "set", "lo", "up"),
            ("-n", ns_b, "link", "set", "lo", "up"),
        ]
        for step in steps:
            r = _ip(*step)
            if r.returncode != 0:
                pytest.skip(f"cannot set up the veth link ({' '.join(step)}): {r.stderr.strip()}")
        yield ns_a, ns_b, addr_a
    finally:
        for ns in made:
            _ip("netns", "del", ns)  # deleting a namespace removes its end of the veth pair


def test_sensors_on_another_host(two_hosts, tmp_path, paper_path):
    ns_a, ns_b, addr_a = two_hosts
    data = yaml.safe_load(paper_path.read_text())
    data["scans"] = 40
    cfg = tmp_path / "paper40.yaml"
    cfg.write_text(yaml.safe_dump(data))
    ref = tmp_path / "ref"
    assert covnet_main(["run", str(cfg), "--out", str(ref), "--no-figures"]) == 0

    router = f"tcp/{addr_a}:7447"
    run_id = f"mh{os.getpid()}"
    common = [str(cfg), "--router", router, "--run", run_id, "--no-figures"]
    mgr = CovnetProcess(
        ["up", *common, "--out", str(tmp_path / "a"), "--nodes", "manager,world,recorder"],
        prefix=["ip", "netns", "exec", ns_a],
    )
    sens = CovnetProcess(
        ["up", *common, "--out", str(tmp_path / "b"), "--nodes", "sensors"],
        prefix=["ip", "netns", "exec", ns_b],
    )
    try:
        assert mgr.wait(timeout=180) == 0, mgr.output() + "\n---\n" + sens.output()
        assert sens.wait(timeout=30) == 0, sens.output()
    finally:
        mgr.stop()
        sens.stop()
    got = json.loads((tmp_path / "a" / "summary.json").read_text())
    want = json.loads((ref / "summary.json").read_text())
    for m in want["metrics"]:
        assert got["metrics"][m]["subsets"] == want["metrics"][m]["subsets"]
        assert got["metrics"][m]["P_diag"] == want["metrics"][m]["P_diag"]
    info = json.loads((tmp_path / "a" / "run.json").read_text())
    assert info["router"] == router
    # the sensors really were elsewhere: their namespace has no route to the manager's loopback
    probe = subprocess.run(
        [
            "ip",
            "netns",
            "exec",
            ns_b,
            sys.executable,
            "-c",
            "import socket; s=socket.socket(); s.settimeout(1); s.connect(('127.0.0.1', 7447))",
        ],
        capture_output=True,
        timeout=20,
    )
    assert probe.returncode != 0
