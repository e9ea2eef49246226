"""``run.json``'s status, once its write has begun, is written whole: a Ctrl-C or SIGTERM during
it is answered right after (:func:`covnet.processes.interrupts.held`).  A ``covnet run``
interrupted at a random moment (the slow suite's seed 7, 1.43 s after its scans) left complete
results with a ``run.json`` that said nothing of how the run ended."""

import json
import os
import signal
import time

import pytest

from covnet.processes import interrupts
from covnet.runs import rundir


@pytest.fixture
def covnets_handlers():
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    for s in before:
        signal.signal(s, interrupts.raise_interrupt)
    interrupts.begin_command()
    yield
    for s, h in before.items():
        signal.signal(s, h)
    interrupts.begin_command()


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_during_the_status_write_is_answered_after_it(
    tmp_path, monkeypatch, covnets_handlers, sig
):
    real = rundir.write_json

    def slow_write(path, data):  # the signal comes while the file is being written
        os.kill(os.getpid(), sig)
        time.sleep(0.05)  # (a handler runs here, between two bytecodes)
        real(path, data)

    monkeypatch.setattr(rundir, "write_json", slow_write)
    with pytest.raises(KeyboardInterrupt):
        rundir.record_end(tmp_path, "completed", "every scan done")
    info = json.loads((tmp_path / rundir.RUN_INFO).read_text())
    assert info["status"] == "completed" and info["ended"] == "every scan done"
    assert interrupts.caused(KeyboardInterrupt())  # answered as covnet's handler answers


def test_held_gives_back_the_handlers_and_holds_nothing_when_no_signal_came(covnets_handlers):
    with interrupts.held():
        assert signal.getsignal(signal.SIGINT) is not interrupts.raise_interrupt
    assert signal.getsignal(signal.SIGINT) is interrupts.raise_interrupt
    assert signal.getsignal(signal.SIGTERM) is interrupts.raise_interrupt
