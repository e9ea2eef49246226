"""The ``covariance_control`` kind (the paper's scenario and its extensions): what the kind
registry (:mod:`covnet.kinds`) knows of it.

Its process roles are ``manager.covariance`` (the fusion centre, or the observer of a peer
network), ``sensors.covariance`` (a sensor, or a peer node) and ``world.covariance``.  Its run
options are ``--seed``, ``--metric`` (the episodes: ``allocation.metrics``) and ``--fusion``
(``fusion.mode``); each is a change of the config, so ``config.json`` records it.  Its commands
are in :mod:`covnet.covariance_control.commands` (``mc``, ``compare`` and ``sweep`` in
:mod:`covnet.covariance_control.batch_commands`), bar ``covnet replay`` and the rebuild of a
network run from its recording (:mod:`covnet.covariance_control.replay`).
"""

from __future__ import annotations

from typing import Any

from covnet.core.metrics import METRICS
from covnet.covariance_control import config
from covnet.covariance_control.fusion_rules import fusion_modes
from covnet.kindkit import KindBase, lazy, seed_option

__all__ = ["KIND"]

_COMMANDS = "covnet.covariance_control.commands"
_BATCH = "covnet.covariance_control.batch_commands"
_VISUAL = "covnet.covariance_control.visual"
_REPLAY = "covnet.covariance_control.replay"
_SIZES = "covnet.covariance_control.network_sizes"


def _metrics(data: dict[str, Any], names: list[str]) -> None:
    for m in names:
        if m not in METRICS:
            raise ValueError(f"unknown metric {m!r}; choose from {sorted(METRICS)}")
    data["allocation"] = {**data["allocation"], "metrics": list(dict.fromkeys(names))}


def _fusion(data: dict[str, Any], mode: str) -> None:
    if mode not in fusion_modes():
        raise ValueError(f"unknown fusion mode {mode!r}; choose from {list(fusion_modes())}")
    data["fusion"] = {**data["fusion"], "mode": mode}


class CovarianceControl(KindBase):
    config = config
    name = config.KIND
    title = "covariance-control"
    roles = {
        "manager": "manager.covariance",
        "sensor": "sensors.covariance",
        "world": "world.covariance",
    }
    options = {"seed": seed_option, "metric": _metrics, "fusion": _fusion}
    commands = {
        "mc": lazy(_BATCH, "mc"),
        "compare": lazy(_BATCH, "compare"),
        "sweep": lazy(_BATCH, "sweep"),
        "replay": lazy(_REPLAY, "command"),
        "bench:alloc": lazy(_COMMANDS, "bench_alloc"),
        "bench:fusion": lazy(_COMMANDS, "bench_fusion"),
        "bench:search": lazy(_COMMANDS, "bench_search"),
        "bench:multitarget": lazy(_COMMANDS, "bench_multitarget"),
        # (cfg, n_sensors, scans) -> config data: the network covnet bench up --sensors runs
        "bench:up-config": lazy(_SIZES, "bench_config"),
    }
    run = staticmethod(lazy(_COMMANDS, "run"))
    after_up = staticmethod(lazy(_COMMANDS, "after_up"))
    up_problem = staticmethod(lazy(_COMMANDS, "up_problem"))
    plot = staticmethod(lazy(_COMMANDS, "plot"))
    tracks = staticmethod(lazy("covnet.covariance_control.results", "tracks"))
    rebuild = staticmethod(lazy(_REPLAY, "rebuild"))
    visual = staticmethod(lazy(_VISUAL, "Visual"))
    run_messages = staticmethod(lazy(_VISUAL, "run_messages"))
    mcap_problem = staticmethod(lazy(_VISUAL, "mcap_problem"))
    check_notes = staticmethod(lazy("covnet.covariance_control.sweep", "check_notes"))

    def older_hashes(self, cfg: Any) -> tuple[str, ...]:
        """The hash of ``required`` and ``excluded`` as written (:func:`~covnet.
        covariance_control.config.older_hashes`)."""
        result: tuple[str, ...] = config.older_hashes(cfg)
        return result

    def episodes(self, cfg: Any) -> list[str]:
        return list(cfg.allocation.metrics)

    def restartable(self, cfg: Any) -> frozenset[str]:
        # the world's truth is a function of the seed alone: it publishes it again on start;
        # a peer node's state is not restartable
        roles = {"world", "recorder"} | ({"sensor"} if cfg.fusion.has_centre else set())
        return frozenset(roles)


KIND = CovarianceControl()
