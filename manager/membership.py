"""Which nodes are alive: liveliness tokens plus an application heartbeat.

A node is *up* at time ``t`` when its last heartbeat arrived within ``failure_timeout_ns`` and
either its liveliness token is alive or that heartbeat arrived after the token went.  So it is
*failed* when

- its token disappeared and nothing was heard from it since (a dead process: zenoh notices
  within milliseconds on loopback), or
- its last heartbeat is older than ``failure_timeout_ns`` (a hung loop keeps its session, hence
  its token, alive; or a link that loses or holds back everything for that long),

and it *rejoins* as soon as it is heard again: a heartbeat after its token went proves the
process alive (a lossy or slow link can end a zenoh session, and with it the token, while the
node runs on and reconnects), so loss on a link is never taken for death for good.  How long a
link may stall before its node counts as failed is ``failure_timeout_ns`` (``network.
failure_timeout_s``; see the README: it must exceed the heartbeat period plus the link's worst
delay, and over TCP a lossy link's retransmission back-off).
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class Membership:
    expected: tuple[str, ...]
    failure_timeout_ns: int
    alive_tokens: set[str] = field(default_factory=set)
    last_heartbeat_ns: dict[str, int] = field(default_factory=dict)
    token_lost_ns: dict[str, int] = field(default_factory=dict)  # when the token went
    refused: set[str] = field(default_factory=set)
    """Nodes whose last heartbeat named another config than the run's (a restart that read an
    edited or other config file): down, whatever they send, until a heartbeat names the run's
    config again (:meth:`refuse`, :meth:`accept`)."""

    def token(self, node_id: str, alive: bool, now_ns: int) -> None:
        if alive:
            self.alive_tokens.add(node_id)
            self.last_heartbeat_ns.setdefault(node_id, now_ns)
        else:
            self.alive_tokens.discard(node_id)
            self.token_lost_ns[node_id] = now_ns

    def down_since_ns(self, node_id: str) -> int | None:
        """When the node was first seen down: its token's loss (nothing heard since), or its
        heartbeat's deadline."""
        last = self.last_heartbeat_ns.get(node_id)
        gone = self.token_lost_ns.get(node_id)
        if node_id not in self.alive_tokens and (last is None or gone is None or last <= gone):
            return gone
        return None if last is None else last + self.failure_timeout_ns

    def heartbeat(self, node_id: str, now_ns: int) -> None:
        self.last_heartbeat_ns[node_id] = now_ns

    def refuse(self, node_id: str) -> None:
        """``node_id``'s heartbeat named another config: down from now on, its measurements no
        sign of life (a restarted sensor with an edited config rejoined through them and was
        fused with numbers its manager did not model, the run ``completed``)."""
        self.refused.add(node_id)

    def accept(self, node_id: str) -> None:
        """``node_id``'s heartbeat named the run's config: no longer refused."""
        self.refused.discard(node_id)

    def resumed(self, last_look_ns: int, now_ns: int, grace_ns: int) -> None:
        """The listener looked last at ``last_look_ns`` and looks again only now, more than the
        timeout later (its process was paused: a SIGSTOP, a swapped-out machine): what the
        nodes sent meanwhile is still on its way (the router is this process).  A node up at
        the last look counts as heard ``grace_ns`` before its timeout runs out from now,
        instead of failed at once (four to five live sensors were failed as a paused manager
        resumed, and the run then differed from ``covnet run``)."""
        floor = now_ns - self.failure_timeout_ns + min(grace_ns, self.failure_timeout_ns)
        for node, last in self.last_heartbeat_ns.items():
            if last < floor and self.is_up(node, last_look_ns):
                self.last_heartbeat_ns[node] = floor

    def is_up(self, node_id: str, now_ns: int) -> bool:
        if node_id in self.refused:
            return False
        last = self.last_heartbeat_ns.get(node_id)
        if last is None or now_ns - last > self.failure_timeout_ns:
            return False
        if node_id in self.alive_tokens:
            return True
        gone = self.token_lost_ns.get(node_id)
        return gone is not None and last > gone  # heard after its token went: alive

    def failed(self, now_ns: int) -> frozenset[str]:
        return frozenset(n for n in self.expected if not self.is_up(n, now_ns))

    def missing_tokens(self) -> list[str]:
        return [n for n in self.expected if n not in self.alive_tokens]
