"""Failure detection: liveliness token plus heartbeat deadline; a node heard again rejoins."""

from __future__ import annotations

from manager.membership import Membership

S = 1_000_000_000


def test_token_loss_fails_at_once_and_rejoin_needs_fresh_heartbeat():
    m = Membership(expected=("S1", "S2"), failure_timeout_ns=S)
    m.token("S1", True, 0)
    m.token("S2", True, 0)
    assert m.failed(0) == frozenset()
    m.token("S1", False, 10)
    assert m.failed(11) == {"S1"} and m.down_since_ns("S1") == 10
    m.token("S1", True, 20)  # back, but its last heartbeat is old
    assert "S1" in m.failed(2 * S)
    m.heartbeat("S1", 2 * S)
    m.heartbeat("S2", 2 * S)
    assert m.failed(2 * S + 1) == frozenset()


def test_hung_node_fails_after_timeout():
    m = Membership(expected=("S1",), failure_timeout_ns=S)
    m.token("S1", True, 0)
    m.heartbeat("S1", 5)
    assert m.failed(S) == frozenset()
    assert m.failed(S + 6) == {"S1"}
    assert m.down_since_ns("S1") == S + 5
    assert m.missing_tokens() == []


def test_heard_after_its_token_went_is_alive_a_link_not_a_death():
    """A lossy link can end a node's zenoh session (its token goes) while the node runs on and
    reconnects; a heartbeat after the token's loss brings it back, token or not."""
    m = Membership(expected=("S1",), failure_timeout_ns=S)
    m.token("S1", True, 0)
    m.heartbeat("S1", 5)
    m.token("S1", False, 10)
    assert m.failed(11) == {"S1"} and m.down_since_ns("S1") == 10
    m.heartbeat("S1", 3 * S)  # heard again, its token still gone
    assert m.failed(3 * S + 1) == frozenset()
    assert m.failed(4 * S + 2) == {"S1"}  # and silent again for longer than the timeout
    assert m.down_since_ns("S1") == 4 * S


def test_a_dead_node_stays_failed():
    m = Membership(expected=("S1",), failure_timeout_ns=S)
    m.token("S1", True, 0)
    m.heartbeat("S1", 5)
    m.token("S1", False, 10)  # died: nothing after this
    for t in (11, S, 10 * S):
        assert m.failed(t) == {"S1"}
    assert m.down_since_ns("S1") == 10


def test_a_listener_that_was_paused_gives_the_nodes_time_to_be_heard():
    """The manager's process (the router too) stopped for 1.5 s: as it resumed it judged every
    quiet sensor by its last heartbeat, before the backlog reached it, and failed four or five
    live ones.  Now a node up at the last look gets ``grace`` from the resume; one already
    failed then (hung, or dead) stays failed."""
    from covnet.clock import SimClock
    from covnet.config import NetworkSpec
    from covnet.wire import messages as msg
    from covnet.wire.bus import InMemoryBus, InMemoryHub
    from manager.loop import Loop

    clock, hub = SimClock(), InMemoryHub()
    net = NetworkSpec(heartbeat_s=0.2, failure_timeout_s=1.0)
    loop = Loop(net, ("S1", "S2"), InMemoryBus(hub), "r", clock)
    node = InMemoryBus(hub)
    tokens = [node.declare_token(msg.alive_key("r", "sensor", s)) for s in ("S1", "S2")]

    def failed():
        return loop.members.failed(clock.now_ns()) - {"world"}  # (no world in this test)

    def beat(sid):
        hb = msg.Heartbeat(role="sensor", node_id=sid, scan=0, t_sent_ns=clock.now_ns(), sent=0)
        node.publish(msg.heartbeat_key("r", "sensor", sid), msg.encode(hb))

    beat("S1")
    clock.advance(0.1)
    loop.poll_membership()  # S2's token but no heartbeat yet: heard at its token
    clock.advance(1.05)
    loop.poll_membership()  # looked 1.05 s later (a paused manager, not a hung node)
    assert failed() == frozenset()
    clock.advance(0.45)  # still nothing heard: the grace (two heartbeat periods) is over
    loop.poll_membership()
    assert failed() == {"S1", "S2"}
    clock.advance(2.0)  # and a failed node does not come back by another pause
    loop.poll_membership()
    assert failed() == {"S1", "S2"}
    assert tokens
