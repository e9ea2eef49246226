"""What a scenario kind's registry entry (``covnet/<kind>/kind.py``) is built from: the run
options every kind shares and the lazy hand-over to the kind's commands.

A kind module is imported by every node process (to load its config), so it stays light: its
commands, figures and experiments are imported when one runs (:func:`lazy`).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any

__all__ = ["lazy", "seed_option"]


def seed_option(data: dict[str, Any], value: int) -> None:
    """``--seed``: the config's ``seed`` (an integer >= 0)."""
    if value < 0:
        raise ValueError(f"must be >= 0, got {value}")
    data["seed"] = value


def lazy(module: str, name: str) -> Callable[..., Any]:
    """``module.name``, imported on the first call: a kind's commands are imported by the
    command that runs them, not by every process that loads a config (start-up time)."""

    def call(*args: Any, **kwargs: Any) -> Any:
        return getattr(importlib.import_module(module), name)(*args, **kwargs)

    call.__name__ = call.__qualname__ = name
    call.__doc__ = f"``{module}.{name}`` (imported when called)."
    return call
