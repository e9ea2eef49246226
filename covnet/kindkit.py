"""What a scenario kind's registry entry (``covnet/<kind>/kind.py``) is built from: the run
options every kind shares and the lazy hand-over to the kind's commands.

A kind module is imported by every node process (to load its config), so it stays light: its
commands, figures and experiments are imported when one runs (:func:`lazy`).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

from covnet.errors import UsageError

__all__ = ["KindBase", "lazy", "seed_option"]


def seed_option(data: dict[str, Any], value: int) -> None:
    """``--seed``: the config's ``seed`` (an integer >= 0)."""
    if value < 0:
        raise ValueError(f"must be >= 0, got {value}")
    data["seed"] = value


class KindBase:
    """What most kinds' entries do alike: the config through the kind's config module
    (``config``: its ``from_dict`` and ``normalised``), any clock and emulation in ``covnet up``,
    restartable sensors and recorder.  A kind overrides what differs."""

    config: Any
    title: str
    mc_options: frozenset[str] | None = None
    """The run options its ``covnet mc`` takes, where fewer than ``Kind.options`` (None: the
    same): what a refusal lists as its options."""

    def from_dict(self, data: object, source: str, base_dir: str | Path | None) -> Any:
        return self.config.from_dict(data, source, base_dir)

    def normalised(self, cfg: Any) -> dict[str, Any]:
        result: dict[str, Any] = self.config.normalised(cfg)
        return result

    def up_problem(
        self, cfg: Any, *, realtime: bool, netns: bool, foxglove: bool = False
    ) -> str | None:
        return None

    def older_hashes(self, cfg: Any) -> tuple[str, ...]:
        """Hashes older covnets gave this config (none here: the kind's normalised form never
        changed for a config it already took)."""
        return ()

    def mcap_problem(self, cfg: Any) -> str | None:
        return None

    def check_notes(self, cfg: Any) -> list[str]:
        """What ``covnet check`` says beside a valid config: a command of the kind that would
        still refuse it (none here)."""
        return []

    def tracks(self, cfg: Any, run_dir: Path) -> list[Any]:
        """No truths and tracks to export (a kind that has them overrides this)."""
        raise UsageError(f"{run_dir}: a {self.title} run has no truths and tracks to export")

    def restartable(self, cfg: Any) -> frozenset[str]:
        """The sensors and the recorder (which continues in a new segment); a world that
        moves with the commands keeps state a restart would lose."""
        return frozenset({"sensor", "recorder"})


def lazy(module: str, name: str) -> Callable[..., Any]:
    """``module.name``, imported on the first call: a kind's commands are imported by the
    command that runs them, not by every process that loads a config (start-up time)."""

    def call(*args: Any, **kwargs: Any) -> Any:
        return getattr(importlib.import_module(module), name)(*args, **kwargs)

    call.__name__ = call.__qualname__ = name
    call.__doc__ = f"``{module}.{name}`` (imported when called)."
    return call
