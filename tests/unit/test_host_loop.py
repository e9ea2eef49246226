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
        missed_command=missed, keep_truth=False, command_ok=None,
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


def test_on_slow_links_a_sensor_hears_every_command():
    one = _sensor("S1", "keep_last")
    assert one.hears(msg.command_key("run1", []))
    assert one.hears(msg.command_key("run1", ["S2"]))
