"""The ``covariance_control`` kind (the paper's scenario and its extensions): what the kind
registry (:mod:`covnet.kinds`) knows of it.

Its process roles are ``manager.covariance`` (the fusion centre, or the observer of a peer
network), ``sensors.covariance`` (a sensor, or a peer node) and ``world.covariance``.  Its run
options are ``--seed``, ``--metric`` (the episodes: ``allocation.metrics``) and ``--fusion``
(``fusion.mode``); each is a change of the config, so ``config.json`` records it.

This module stays light (a node process imports it to load its config): the commands import
what they run when they run.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from covnet.covariance_control import config

__all__ = ["KIND"]


def _seed(data: dict[str, Any], value: int) -> None:
    if value < 0:
        raise ValueError(f"must be >= 0, got {value}")
    data["seed"] = value


def _metrics(data: dict[str, Any], names: list[str]) -> None:
    from covnet.core.metrics import METRICS

    for m in names:
        if m not in METRICS:
            raise ValueError(f"unknown metric {m!r}; choose from {sorted(METRICS)}")
    data["allocation"] = {**data["allocation"], "metrics": list(dict.fromkeys(names))}


def _fusion(data: dict[str, Any], mode: str) -> None:
    if mode not in config.FUSION_MODES:
        raise ValueError(f"unknown fusion mode {mode!r}; choose from {list(config.FUSION_MODES)}")
    data["fusion"] = {**data["fusion"], "mode": mode}


def _command(name: str) -> Callable[..., int]:
    """``commands.<name>``, imported when the command runs (start-up time of every node)."""

    def call(*args: Any, **kwargs: Any) -> int:
        from covnet.covariance_control import commands

        result: int = getattr(commands, name)(*args, **kwargs)
        return result

    call.__name__ = name
    return call


class CovarianceControl:
    name = config.KIND
    title = "covariance-control"
    roles = {
        "manager": "manager.covariance",
        "sensor": "sensors.covariance",
        "world": "world.covariance",
    }
    options = {"seed": _seed, "metric": _metrics, "fusion": _fusion}
    commands = {
        "compare": _command("compare"),
        "sweep": _command("sweep"),
        "replay": _command("replay"),
        "bench:alloc": _command("bench_alloc"),
        "bench:fusion": _command("bench_fusion"),
    }

    def from_dict(self, data: object, source: str, base_dir: str | Path | None) -> Any:
        return config.from_dict(data, source, base_dir)

    def normalised(self, cfg: Any) -> dict[str, Any]:
        return config.normalised(cfg)

    def episodes(self, cfg: Any) -> list[str]:
        return list(cfg.allocation.metrics)

    def run(self, cfg: Any, out: Path, *, figures: bool) -> int:
        from covnet.covariance_control import commands

        return commands.run(cfg, out, figures=figures)

    def after_up(self, cfg: Any, out: Path, *, figures: bool) -> None:
        from covnet.covariance_control import commands

        commands.after_up(cfg, out, figures=figures)

    def up_problem(self, cfg: Any, *, realtime: bool, netns: bool) -> str | None:
        from covnet.covariance_control import commands

        return commands.up_problem(cfg, realtime=realtime, netns=netns)

    def sensors_restartable(self, cfg: Any) -> bool:
        return bool(cfg.fusion.mode != "peer")  # a peer node's state is not restartable

    def plot(self, run_dir: Path) -> list[Path]:
        from covnet.covariance_control import commands

        return commands.plot(run_dir)


KIND = CovarianceControl()
