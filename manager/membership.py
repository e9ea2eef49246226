"""Which nodes are alive: liveliness tokens plus an application heartbeat.

A node is *failed* when its liveliness token disappears (a dead process: zenoh notices within
milliseconds on loopback) or when its last heartbeat is older than ``failure_timeout_ns`` (a
hung loop keeps its session, hence its token, alive).  A failed node *rejoins* when its token is
back and a fresh heartbeat has arrived.
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

    def token(self, node_id: str, alive: bool, now_ns: int) -> None:
        if alive:
            self.alive_tokens.add(node_id)
            self.last_heartbeat_ns.setdefault(node_id, now_ns)
        else:
            self.alive_tokens.discard(node_id)
            self.token_lost_ns[node_id] = now_ns

    def down_since_ns(self, node_id: str) -> int | None:
        """When the node was first seen down: its token's loss, or its heartbeat's deadline."""
        if node_id not in self.alive_tokens:
            return self.token_lost_ns.get(node_id)
        last = self.last_heartbeat_ns.get(node_id)
        return None if last is None else last + self.failure_timeout_ns

    def heartbeat(self, node_id: str, now_ns: int) -> None:
        self.last_heartbeat_ns[node_id] = now_ns

    def is_up(self, node_id: str, now_ns: int) -> bool:
        if node_id not in self.alive_tokens:
            return False
        last = self.last_heartbeat_ns.get(node_id)
        return last is not None and now_ns - last <= self.failure_timeout_ns

    def failed(self, now_ns: int) -> frozenset[str]:
        return frozenset(n for n in self.expected if not self.is_up(n, now_ns))

    def missing_tokens(self) -> list[str]:
        return [n for n in self.expected if n not in self.alive_tokens]
