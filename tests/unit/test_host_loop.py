"""The hosted sensors' one loop (``sensors.protocol.HostLoop``) hears every command and gives
each sensor those its own subscription would have received: ``_Sensor.hears`` agrees with
the key expression a sensor alone subscribes to (``command_keyexpr(run, id)``, zenoh's
``$*~<id>~$*``), for every command key of random enabled sets."""

from __future__ import annotations

import numpy as np
import pytest

from covnet.clock import WallClock
from covnet.config import NetworkSpec
from covnet.wire import messages as msg
from covnet.wire.bus import InMemoryBus, keyexpr_matches
from sensors.protocol import _Sensor

IDS = ["S1", "S1.1", "S11", "S1.10", "A", "AA", "S2.1", "x1"]


def _sensor(sid: str, missed: str | None) -> _Sensor:
    return _Sensor(
        sid, InMemoryBus(), "run1", WallClock(), NetworkSpec(), truth_ok=lambda tr: True,
        respond=lambda c, t: None,  # type: ignore[arg-type,return-value]
        scans=10**6, missed_command=missed, keep_truth=False, command_ok=None,
    )  # fmt: skip


@pytest.mark.parametrize("seed", range(10))
def test_a_hosted_sensor_hears_what_its_own_subscription_would(seed):
    rng = np.random.default_rng(seed)
    sensors = [_sensor(sid, None) for sid in IDS]
    for _ in range(50):
        enabled = [sid for sid in IDS if rng.random() < 0.4]
        rng.shuffle(enabled)
        key = msg.command_key("run1", enabled)
        for one in sensors:
            own = keyexpr_matches(msg.command_keyexpr("run1", one.id), key)
            assert one.hears(key) == own == (one.id in enabled)
            assert one.hears(key, key.rpartition("/")[2]) == own


def test_on_slow_links_a_sensor_hears_every_command():
    one = _sensor("S1", "keep_last")
    assert one.hears(msg.command_key("run1", []))
    assert one.hears(msg.command_key("run1", ["S2"]))


@pytest.mark.parametrize("missed", [None, "keep_last", "on", "off"])
def test_a_hosts_enabled_set_gives_what_the_commands_tuple_gives(missed):
    """``accept(cmd, frozenset(cmd.enabled))`` (the host loop's, the set made once per
    command) queues, counts and remembers what ``accept(cmd)`` does, over random commands."""
    rng = np.random.default_rng(3)
    a, b = _sensor("S1.1", missed), _sensor("S1.1", missed)
    scan = 0
    for _ in range(200):
        scan += int(rng.integers(1, 3))
        enabled = [sid for sid in IDS if rng.random() < 0.5]
        cmd = msg.Command(scan, scan * 1.0, tuple(enabled), 5, episode=int(rng.integers(0, 2)))
        a.accept(cmd)
        b.accept(cmd, frozenset(cmd.enabled))
        assert list(a.pending) == list(b.pending)
        assert (a.stats, a.newest, a.last_on, a.last_scan) == (
            b.stats, b.newest, b.last_on, b.last_scan,
        )  # fmt: skip
    assert a.stats.enabled_scans > 50
