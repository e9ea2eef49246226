"""One stop request delivered twice (GNU ``timeout -s INT`` signals the command, then its own
process group) is one interruption: the second signal, a moment after the first, made ``covnet
up`` take it for a second Ctrl-C and SIGKILL every node (a recording without its footer,
``network.json``'s counters lost).  A later one is a second request, as before."""

from __future__ import annotations

import subprocess
import sys

SCRIPT = r"""
import os, signal, time
from covnet.processes import interrupts
signal.signal(signal.SIGINT, interrupts.raise_interrupt)
raised, sent = 0, []
for gap in (0.0, 0.0, 1.0):  # two at once (the duplicate), then one a second later
    time.sleep(gap)
    try:
        sent.append(time.monotonic())
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.1)  # the handler runs here
    except KeyboardInterrupt:
        raised += 1
print(raised, sent[1] - sent[0])
"""


def test_a_duplicate_signal_is_the_same_request():
    from covnet.processes.interrupts import SAME_REQUEST_S

    out = subprocess.run(
        [sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=60, check=True
    )
    raised, apart = out.stdout.split()
    if float(apart) < SAME_REQUEST_S:  # (a machine stalled for longer sent two requests)
        assert raised == "2", out
