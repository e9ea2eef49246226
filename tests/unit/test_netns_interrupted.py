"""A Ctrl-C while ``ip netns add`` ran (the namespace made, its return not seen) left the
namespace behind, while the launcher said every namespace was removed: 3 of 12 interrupts
during set-up.  Each place that adds one now deletes it whatever happened.  (No root needed:
``ip`` is replaced by a recorder that raises the interrupt as the add returns.)"""

from __future__ import annotations

import subprocess

import pytest

from covnet.processes import netns_launch
from covnet.processes.netem import detect, link


class _Ip:
    def __init__(self) -> None:
        self.calls: list[tuple[str, ...]] = []

    def __call__(self, *args: str, timeout: float = 20.0) -> subprocess.CompletedProcess[str]:
        self.calls.append(args)
        if args[:2] == ("netns", "add"):
            raise KeyboardInterrupt  # the add done, the Ctrl-C before its return was seen
        return subprocess.CompletedProcess(args, 0, "", "")

    def deleted(self) -> list[str]:
        return [a[2] for a in self.calls if a[:2] == ("netns", "del")]


def test_the_launchers_namespace(monkeypatch):
    ip = _Ip()
    monkeypatch.setattr(netns_launch, "run_ip", ip)
    with pytest.raises(KeyboardInterrupt), netns_launch._namespace("cvn1m"):
        pass
    assert ip.deleted() == ["cvn1m"]


def test_the_netem_probes_namespace(monkeypatch):
    ip = _Ip()
    monkeypatch.setattr(detect, "run_ip", ip)
    monkeypatch.setattr(detect, "can_make_namespaces", lambda: True)
    monkeypatch.setattr(detect.shutil, "which", lambda name: f"/usr/sbin/{name}")
    with pytest.raises(KeyboardInterrupt):
        detect.netem_available()
    (added,) = [a[2] for a in ip.calls if a[:2] == ("netns", "add")]
    assert ip.deleted() == [added]


def test_the_links_namespaces(monkeypatch):
    ip = _Ip()
    monkeypatch.setattr(link, "run_ip", ip)
    monkeypatch.setattr(link, "can_make_namespaces", lambda: True)
    with pytest.raises(KeyboardInterrupt), link.namespaces(2):
        pass
    (added,) = [a[2] for a in ip.calls if a[:2] == ("netns", "add")]
    assert ip.deleted() == [added]


def test_a_link_whose_forwarder_died_is_said_and_recorded():
    """A link forwarder killed mid-run cut its sensor off: the run said only that the sensor
    failed, and the link's counters were null without a reason."""
    import sys
    from types import SimpleNamespace

    from covnet.processes.netem.tun_link import Forwarder

    proc = subprocess.Popen(
        [sys.executable, "-c", "import os; os._exit(9)"], stdout=subprocess.PIPE
    )
    proc.wait(timeout=30)
    fw = Forwarder(proc)
    fw.stop()
    assert fw.died == 9 and fw.stats is None
    live = subprocess.Popen(
        [sys.executable, "-c", "import time; time.sleep(30)"], stdout=subprocess.PIPE
    )
    alive = Forwarder(live)
    alive.stop(grace=5)
    assert alive.died is None  # stopped by us: not a death
    topo = SimpleNamespace(links={
        "S3": SimpleNamespace(info=SimpleNamespace(died=-9)),
        "S4": SimpleNamespace(info=SimpleNamespace(died=None)),
    })  # fmt: skip
    (line,) = netns_launch.dead_links(topo)
    assert line.startswith("the link of S3 died during the run") and "exit status -9" in line
