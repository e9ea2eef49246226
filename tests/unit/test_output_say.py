"""covnet up says its nodes' lines through :func:`covnet.processes.output.say`."""

from __future__ import annotations

import sys
import threading

from covnet.processes import output


def test_lines_said_from_many_threads_stay_whole(capfd):
    """The launcher says each node's lines from that node's reader thread; two nodes' lines
    ran into one (``print`` writes the text and the newline apart)."""
    output.reset()
    go = threading.Event()

    def node(i: int) -> None:
        go.wait()
        for j in range(400):
            output.say(f"[S{i}] line {j} " + "x" * 50)

    threads = [threading.Thread(target=node, args=(i,)) for i in range(8)]
    old = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)  # switch threads as often as possible
    try:
        for t in threads:
            t.start()
        go.set()
        for t in threads:
            t.join()
    finally:
        sys.setswitchinterval(old)
    lines = capfd.readouterr().out.splitlines()
    assert len(lines) == 8 * 400
    assert all(s.startswith("[S") and s.count("[S") == 1 and s.endswith("x") for s in lines)
