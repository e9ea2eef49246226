"""The ``mobile`` kind (mobile sensors choosing motion modes and targets by LP, issue 7): what
the kind registry (:mod:`covnet.kinds`) knows of it.

Process roles: ``manager.mobile``, ``sensors.mobile``, ``world.mobile``.  Run options:
``--seed`` and ``--solver`` (each a change of the config).  Commands: ``covnet mc`` (seeds in
parallel) and ``covnet bench mobile``.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from covnet.mobile import config

__all__ = ["KIND"]


def _seed(data: dict[str, Any], value: int) -> None:
    if value < 0:
        raise ValueError(f"must be >= 0, got {value}")
    data["seed"] = value


def _solver(data: dict[str, Any], value: str) -> None:
    from covnet.core.mobile.decision import SOLVERS

    if value not in SOLVERS:
        raise ValueError(f"unknown solver {value!r}; choose from {sorted(SOLVERS)}")
    data["solver"] = value


def _command(name: str) -> Callable[..., int]:
    """``commands.<name>``, imported when the command runs (start-up time of every node)."""

    def call(*args: Any, **kwargs: Any) -> int:
        from covnet.mobile import commands

        result: int = getattr(commands, name)(*args, **kwargs)
        return result

    call.__name__ = name
    return call


class Mobile:
    name = config.KIND
    title = "mobile"
    roles = {"manager": "manager.mobile", "sensor": "sensors.mobile", "world": "world.mobile"}
    options = {"seed": _seed, "solver": _solver}
    commands = {"mc": _command("mc"), "bench:mobile": _command("bench")}

    def from_dict(self, data: object, source: str, base_dir: str | Path | None) -> Any:
        return config.from_dict(data, source, base_dir)

    def normalised(self, cfg: Any) -> dict[str, Any]:
        return config.normalised(cfg)

    def episodes(self, cfg: Any) -> list[str]:
        return [str(cfg.solver)]

    def run(self, cfg: Any, out: Path, *, figures: bool) -> int:
        from covnet.mobile import commands

        return commands.run(cfg, out, figures=figures)

    def after_up(self, cfg: Any, out: Path, *, figures: bool) -> None:
        from covnet.mobile import commands

        commands.after_up(cfg, out, figures=figures)

    def up_problem(self, cfg: Any, *, realtime: bool, netns: bool) -> str | None:
        return None

    def sensors_restartable(self, cfg: Any) -> bool:
        return True

    def plot(self, run_dir: Path) -> list[Path]:
        from covnet.mobile.plots import make_figure

        return [make_figure(run_dir)]


KIND = Mobile()
