"""A second ``covnet up`` given the ``--router`` of a running one (hunt 11): its manager failed
to bind ~2 s after the start, but by then its world and sensors had joined the running run on
that port (its sensors took their truths, its estimate drifted from ``covnet run``'s, and it
waited ``scan_timeout_s`` every scan).  The launcher now probes the router's address before it
starts anything, and refuses."""

from __future__ import annotations

import socket

import pytest
from multiproc import CovnetProcess

from covnet.processes.up import free_port, router_in_use

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]


def test_a_router_address_in_use_is_refused_before_any_node_starts(tmp_path, paper_path):
    port = free_port()
    with socket.socket() as other:  # what listens there already: another run's router
        other.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        other.bind(("127.0.0.1", port))
        other.listen()
        assert router_in_use(f"tcp/127.0.0.1:{port}") is not None
        out = tmp_path / "second"
        p = CovnetProcess(["up", str(paper_path), "--router", f"tcp/127.0.0.1:{port}",
                           "--out", str(out), "--no-figures"])  # fmt: skip
        try:
            rc = p.wait(timeout=60)
        finally:
            p.stop()
        assert rc == 1, p.output()
        assert f"tcp/127.0.0.1:{port} is in use" in p.output(), p.output()
        assert "nothing was started" in p.output()
        assert not (out / "processes.json").exists()  # no node ever ran
    # free again: no refusal (a port 0 or another transport is never probed)
    assert router_in_use(f"tcp/127.0.0.1:{port}") is None
    assert router_in_use("tcp/127.0.0.1:0") is None
