"""The ``passive`` kind (fast association of angle-only measurements from three passive
sensors, issue 6): what the kind registry (:mod:`covnet.kinds`) knows of it.

Process roles: ``manager.passive``, ``sensors.passive``, ``world.passive``.  Run option:
``--seed`` (a change of the config).  Commands: ``covnet mc`` (the §9 protocol) and
``covnet bench passive``.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from covnet.passive import config

__all__ = ["KIND"]


def _seed(data: dict[str, Any], value: int) -> None:
    if value < 0:
        raise ValueError(f"must be >= 0, got {value}")
    data["seed"] = value


def _command(name: str) -> Callable[..., int]:
    """``commands.<name>``, imported when the command runs (start-up time of every node)."""

    def call(*args: Any, **kwargs: Any) -> int:
        from covnet.passive import commands

        result: int = getattr(commands, name)(*args, **kwargs)
        return result

    call.__name__ = name
    return call


class Passive:
    name = config.KIND
    title = "passive"
    roles = {"manager": "manager.passive", "sensor": "sensors.passive", "world": "world.passive"}
    options = {"seed": _seed}
    commands = {"mc": _command("mc"), "bench:passive": _command("bench")}

    def from_dict(self, data: object, source: str, base_dir: str | Path | None) -> Any:
        return config.from_dict(data, source, base_dir)

    def normalised(self, cfg: Any) -> dict[str, Any]:
        return config.normalised(cfg)

    def episodes(self, cfg: Any) -> list[str]:
        return [str(cfg.association.method)]

    def run(self, cfg: Any, out: Path, *, figures: bool) -> int:
        from covnet.passive import commands

        return commands.run(cfg, out, figures=figures)

    def after_up(self, cfg: Any, out: Path, *, figures: bool) -> None:
        from covnet.passive import commands

        commands.after_up(cfg, out, figures=figures)

    def up_problem(self, cfg: Any, *, realtime: bool, netns: bool) -> str | None:
        return None

    def sensors_restartable(self, cfg: Any) -> bool:
        return True

    def plot(self, run_dir: Path) -> list[Path]:
        from covnet.passive.plots import scene_figure

        return [scene_figure(run_dir)]


KIND = Passive()
