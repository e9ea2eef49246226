"""Messages from nodes that are not the run's: the manager refuses them before they touch a
sensor's numbers or the fused scan (found by a rogue client on the real bus):

- a measurement on the key of a sensor id the config does not have was judged like a
  member's; with slow links (``accept_unsolicited``) it was taken into the scan and the
  fusion died on ``ids.index`` (``x not in tuple``); without, it still made a phantom
  sensor in ``network.json`` (``sent 99999, lost 99998``) and a bitmap in the manager;
- a measurement of a scan ahead of the manager's, on a member's key, counted its ``seq``
  before it was refused (``sent 99000, lost 98906`` for S1);
- a heartbeat of a node the run does not have put its ``rejected`` counts in
  ``rejected_by_node``."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from covnet.clock import WallClock
from covnet.config import NetworkSpec
from covnet.wire import messages as msg
from covnet.wire.bus import InMemoryBus, Sample
from manager.covariance import CovarianceLogic
from manager.loop import Loop

pytestmark = pytest.mark.usefixtures("room_in_the_names_cache")


def _setup(paper, unsolicited: bool):
    loop = Loop(NetworkSpec(), paper.sensor_ids, InMemoryBus(), "st", WallClock())
    logic = CovarianceLogic(paper, loop)
    logic.start_episode(0)
    decision = logic.decide(0, 1, frozenset())
    logic.ahead(0, 1)
    loop.accept_unsolicited = unsolicited
    return loop, logic, decision


def _meas(sid: str, scan: int, seq: int) -> msg.Measurement:
    return msg.Measurement(
        sensor_id=sid, scan=scan, t=0.1 * scan, z=np.zeros((1, 2)), R=1e12 * np.eye(2),
        t_sent_ns=1000, episode=0, seq=seq,
    )  # fmt: skip


@pytest.mark.parametrize("unsolicited", [False, True])
@pytest.mark.parametrize("together", [False, True])
def test_a_measurement_of_a_sensor_the_run_does_not_have_is_refused(paper, unsolicited, together):
    loop, logic, decision = _setup(paper, unsolicited)
    waiting, got = set(decision.enabled), {}
    batch = [
        Sample(msg.measurement_key("st", f"Z{i}"), msg.encode(_meas(f"Z{i}", 1, 99_999)), i)
        for i in range(20)
    ]
    if together:
        loop._take_many(batch, 0, 1, waiting, got, logic.usable, msg.Measurement, None)
    else:
        for s in batch:
            loop._take(s, 0, 1, waiting, got, logic.usable, msg.Measurement)
    assert got == {}
    assert loop.stats.rejected == {"unknown_sensor": 20}
    assert loop.stats.seq == {} and loop.stats.lost == 0
    assert loop.stats.sensors() == {}
    logic.fuse(0, 1, got)  # and the scan fuses (the fusion died on an unknown id)


def test_a_measurement_of_a_later_scan_does_not_count_its_number(paper):
    loop, logic, decision = _setup(paper, False)
    waiting, got = set(decision.enabled), {}
    s1 = paper.sensor_ids[0]
    key = msg.measurement_key("st", s1)
    loop._take(Sample(key, msg.encode(_meas(s1, 5, 99_000)), 1), 0, 1, waiting, got,
               logic.usable, msg.Measurement)  # fmt: skip
    assert loop.stats.rejected == {"wrong_scan": 1}
    assert loop.stats.sensors().get(s1, {}).get("sent", 0) == 0
    # nor in the sensor's own outcome (sent = on_time + late + rejected + lost holds)
    assert loop.stats.sensors().get(s1, {}).get("rejected", 0) == 0
    assert loop.stats.lost == 0


def test_a_heartbeat_of_a_node_the_run_does_not_have_is_refused(paper):
    loop, _, _ = _setup(paper, False)
    for role, node in (("sensor", "Z9"), ("sensor", paper.sensor_ids[0]), ("recorder", "recorder")):
        hb = msg.Heartbeat(role, node, 0, 1000, rejected={"x": 5})
        loop.hb_sub.channel.put(Sample(msg.heartbeat_key("st", role, node), msg.encode(hb), 1))
    loop.poll_membership()
    assert sorted(loop.stats.node_rejected) == sorted([paper.sensor_ids[0], "recorder"])
    assert loop.stats.rejected == {"unknown_node": 1}


def test_a_token_with_an_invalid_node_id_while_the_manager_waits_is_not_a_crash(paper, monkeypatch):
    """``wait_ready`` parsed the liveliness events it waited on without the check
    ``poll_membership`` has: a token ``alive/sensor/<65 characters>`` declared before READY
    ended the manager in a ValueError."""
    import threading

    from covnet.wire.bus import LivelinessEvent
    from manager.loop import ManagerError

    loop = Loop(
        NetworkSpec(ready_timeout_s=0.3), paper.sensor_ids, InMemoryBus(), "st", WallClock()
    )
    monkeypatch.setattr(loop, "poll_membership", lambda: None)  # only the wait reads events
    for key in (f"covnet/st/alive/sensor/{'X' * 65}", "covnet/st/alive"):
        loop.live_sub.channel.put(LivelinessEvent(key, True))
    with pytest.raises(ManagerError, match="nodes not alive"):
        loop.wait_ready(threading.Event())
    assert loop.stats.rejected == {"bad_key": 2}


def test_a_done_token_of_another_session_stops_the_run_saying_why(paper):
    """A third-party session declaring ``alive/manager/done`` made every node leave, and the
    manager then failed with "all 8 sensors are excluded": it now stops at once and names
    the forged token; its own ``done`` (as it ends) is no such event."""
    from covnet.wire.bus import LivelinessEvent
    from manager.loop import ManagerError

    loop = Loop(NetworkSpec(), paper.sensor_ids, InMemoryBus(), "st", WallClock())
    loop.membership_changes(1, frozenset())  # nothing yet
    loop.live_sub.channel.put(LivelinessEvent(msg.done_key("st"), True))
    with pytest.raises(ManagerError, match="another session declared the run's end"):
        loop.membership_changes(2, frozenset())
    assert loop.stats.rejected == {"forged_done": 1}
    own = Loop(NetworkSpec(), paper.sensor_ids, InMemoryBus(), "st2", WallClock())
    own.end()
    own.live_sub.channel.put(LivelinessEvent(msg.done_key("st2"), True))
    own.poll_membership()
    assert not own.forged_done and own.stats.rejected == {}


def test_an_enabled_sensor_dropped_as_failed_that_answers_after_all_is_taken(paper):
    """Under load the wait may take an enabled sensor for failed (its heartbeat late) and stop
    waiting for it; its measurement, arriving before the scan is fused, was refused as
    ``not_enabled`` (a flaky in-process run: ``rejected {'not_enabled': 1}``). It is this
    scan's answer of an enabled sensor: taken. One never enabled is still refused."""
    loop, logic, decision = _setup(paper, False)
    off = [sorted(decision.enabled)[-1]]  # the scan as if this one were not enabled
    enabled = sorted(set(decision.enabled) - set(off))
    late = enabled[0]
    loop.members.is_up = lambda sid, now: sid != late  # type: ignore[method-assign]
    bus = InMemoryBus(loop.bus._hub, name="sensors")  # the sensors' side of the same hub
    for i, sid in enumerate(enabled[1:], start=1):
        bus.publish(msg.measurement_key("st", sid), msg.encode(_meas(sid, 1, i)))

    def answers_late():  # the dropped sensor, and a stray of one not enabled, come after
        bus.publish(msg.measurement_key("st", late), msg.encode(_meas(late, 1, 1)))
        bus.publish(msg.measurement_key("st", off[0]), msg.encode(_meas(off[0], 1, 1)))

    poll = loop.poll_membership
    loop.poll_membership = lambda: (poll(), answers_late())[0]  # type: ignore[method-assign]
    got = loop.collect(0, 1, set(enabled), time.monotonic() + 5.0, threading.Event(),
                       logic.usable)  # fmt: skip
    assert set(got) == set(enabled)
    assert loop.stats.rejected == {"not_enabled": 1}  # the one never enabled


def test_not_ready_names_the_setting_and_counts_a_long_list():
    from manager.loop import NAMED_NODES, not_ready

    assert not_ready(30.0, ["S1", "S2"], []) == (
        "nodes not alive after 30.0 s (network.ready_timeout_s): ['S1', 'S2']"
    )
    assert not_ready(5.0, [], ["W"]) == (
        "nodes alive but sent no heartbeat within 5.0 s (network.ready_timeout_s): ['W']"
    )
    ids = [f"S{i}" for i in range(256)]
    said = not_ready(30.0, ids, [])
    assert said.startswith("nodes not alive after 30.0 s (network.ready_timeout_s): ['S0', 'S1'")
    assert said.endswith(f"'S{NAMED_NODES - 1}', ... and {256 - NAMED_NODES} more (256 in all)]")
    assert f"'S{NAMED_NODES}'" not in said
