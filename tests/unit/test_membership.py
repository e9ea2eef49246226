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
