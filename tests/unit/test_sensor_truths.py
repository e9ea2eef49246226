"""A sensor keeps the truths of scans to come (the world sends a short run's truth once, up
front); a rogue client's truths of scans that never come (scan 10^9 + i) were kept for the whole
run, and 300 of them grew every sensor by ~100 MB.  A truth of a scan outside ``1..scans`` is
now counted ``bad_scan`` and dropped, in every kind (``scans`` is a required argument of
``serve``: the kinds' sensor loops pass their run's)."""

from __future__ import annotations

import numpy as np
import pytest

from covnet.clock import WallClock
from covnet.config import NetworkSpec
from covnet.wire import messages as msg
from covnet.wire.bus import InMemoryBus
from sensors.protocol import _Sensor


def _sensor(scans, *, keep_truth, missed=None):
    return _Sensor(
        "S1", InMemoryBus(), "run1", WallClock(), NetworkSpec(), truth_ok=lambda tr: True,
        respond=lambda c, t: None,  # type: ignore[arg-type,return-value]
        scans=scans, missed_command=missed, keep_truth=keep_truth, command_ok=None,
    )  # fmt: skip


@pytest.mark.parametrize("keep_truth", [False, True])
def test_a_truth_of_a_scan_outside_the_run_is_refused(keep_truth):
    one = _sensor(10, keep_truth=keep_truth)
    for k in (0, 1, 10, 11, 10**9):
        one.take_truth(msg.Truth(k, 0.1 * k, ("T1",), np.zeros((1, 4))))
    assert sorted(one.truths) == [1, 10]
    assert one.stats.rejected == {"bad_scan": 3}


@pytest.mark.parametrize("missed", [None, "keep_last", "off"])
def test_a_command_of_a_scan_outside_the_run_is_refused(missed):
    """On slow links a sensor filled in every scan up to a command's (one fallback command
    each): a rogue's command of scan 10**9 took hours of CPU and the memory of a queue of 10**9
    commands.  A command of a scan outside ``1..scans`` is counted ``bad_scan``, in every mode,
    and changes nothing."""
    one = _sensor(10, keep_truth=False, missed=missed)
    for k in (0, 11, 10**9):
        one.accept(msg.Command(k, float(k), ("S1",), 1))
    assert one.stats.rejected == {"bad_scan": 3}
    assert not one.pending and one.newest == (-1, 0) and one.stats.missed_commands == 0
    one.accept(msg.Command(3, 3.0, ("S1",), 1))
    assert [c.scan for c in one.pending] == [3]  # (keep_last: off before its first command)
    assert one.stats.missed_commands == (0 if missed is None else 2)


def test_a_sensor_no_scan_enables_keeps_only_the_truths_near_the_newest():
    """A run above TRUTH_UPFRONT_MAX_SCANS (truth window by window): a sensor drops its old
    truths as it answers a command; one that no scan enables answered nothing and kept every
    truth (0.5 kB a scan: 10 MB over the soak's 20 000 scans).  Without a command waiting it
    keeps those within TRUTHS_NEAR of the newest; a waiting command's truth is never dropped."""
    from sensors.protocol import TRUTHS_NEAR

    one = _sensor(20_000, keep_truth=False)
    for k in range(1, 5001):
        one.take_truth(msg.Truth(k, 0.1 * k, ("T1",), np.zeros((1, 4))))
        assert len(one.truths) <= 2 * TRUTHS_NEAR + 1
    assert 5000 in one.truths and 5000 - TRUTHS_NEAR in one.truths
    # a command waiting for its truth: nothing is dropped while it waits
    one.accept(msg.Command(6000, 600.0, ("S1",), 1))
    for k in range(5001, 6001):
        one.take_truth(msg.Truth(k, 0.1 * k, ("T1",), np.zeros((1, 4))))
    assert 6000 in one.truths and len(one.truths) > 1000
    # a sensor that keeps the run's truth (up to TRUTH_UPFRONT_MAX_SCANS) keeps all of it
    keep = _sensor(500, keep_truth=True)
    for k in range(1, 501):
        keep.take_truth(msg.Truth(k, 0.1 * k, ("T1",), np.zeros((1, 4))))
    assert len(keep.truths) == 500
