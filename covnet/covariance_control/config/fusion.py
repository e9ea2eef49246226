"""The ``fusion:`` table: the fusion structure (a centre, or peer nodes and their graph)."""

from __future__ import annotations

from typing import Literal

from covnet.config import ConfigModel, Str
from covnet.covariance_control.config.fields import FusionMode, TrackRule
from covnet.covariance_control.fusion_rules import has_centre

PEER_GRAPHS = ("full", "ring", "star", "custom")


class PeerSpec(ConfigModel):
    """Peer-to-peer mode: which sensors exchange local tracks (``graph``; ``custom`` takes
    undirected ``edges`` by sensor id; ``star`` has ``hub`` at its centre, default the first
    sensor) and how each node fuses what it receives (``rule``)."""

    rule: TrackRule = "info"
    graph: Literal["full", "ring", "star", "custom"] = "full"
    hub: Str | None = None
    edges: tuple[tuple[Str, Str], ...] = ()


class FusionSpec(ConfigModel):
    """The fusion structure (README, "Decentralized fusion"): ``central`` (the manager fuses
    raw measurements), ``info`` / ``ci`` (sensors run local filters and publish local tracks;
    the manager fuses them by information-matrix fusion or covariance intersection), ``peer``
    (no fusion centre: nodes fuse their neighbours' tracks, see :class:`PeerSpec`).
    ``ci_objective``: what the covariance-intersection weights minimise (``det``, ``trace``)
    or ``fast`` (closed-form weights ``w_i ∝ 1 / tr P_i``)."""

    mode: FusionMode = "central"
    ci_objective: Literal["det", "trace", "fast"] = "det"
    peer: PeerSpec = PeerSpec()

    @property
    def rule(self) -> str:
        """The fusion rule in effect (``FUSION_RULES``): ``mode``, or in peer mode
        ``peer.rule``."""
        return self.peer.rule if not self.has_centre else self.mode

    @property
    def has_centre(self) -> bool:
        """A fusion centre fuses (else the peer nodes do: ``mode: peer``)."""
        return has_centre(self)
