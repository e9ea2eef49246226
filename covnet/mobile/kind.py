"""The ``mobile`` kind (mobile sensors choosing motion modes and targets by LP, issue 7): what
the kind registry (:mod:`covnet.kinds`) knows of it.

Process roles: ``manager.mobile``, ``sensors.mobile``, ``world.mobile``.  Run options:
``--seed`` and ``--solver`` (each a change of the config).  Commands (in
:mod:`covnet.mobile.commands`): ``covnet mc`` (seeds in parallel) and ``covnet bench mobile``;
``covnet replay`` and the rebuild of a network run from its recording are
:mod:`covnet.mobile.replay`'s.
"""

from __future__ import annotations

from typing import Any

from covnet.kindkit import KindBase, lazy, seed_option
from covnet.mobile import config

__all__ = ["KIND"]

_COMMANDS = "covnet.mobile.commands"
_VISUAL = "covnet.mobile.visual"
_REPLAY = "covnet.mobile.replay"


def _solver(data: dict[str, Any], value: str) -> None:
    if value not in config.SOLVERS:
        raise ValueError(f"unknown solver {value!r}; choose from {sorted(config.SOLVERS)}")
    data["solver"] = value


class Mobile(KindBase):
    config = config
    name = config.KIND
    title = "mobile"
    roles = {"manager": "manager.mobile", "sensor": "sensors.mobile", "world": "world.mobile"}
    options = {"seed": seed_option, "solver": _solver}
    mc_options = frozenset[str]()  # its mc runs seeds 0..N-1 with the config's solver
    commands = {
        "mc": lazy(_COMMANDS, "mc"),
        "replay": lazy(_REPLAY, "command"),
        "bench:mobile": lazy(_COMMANDS, "bench"),
    }
    run = staticmethod(lazy(_COMMANDS, "run"))
    after_up = staticmethod(lazy(_COMMANDS, "after_up"))
    plot = staticmethod(lazy(_COMMANDS, "plot"))
    tracks = staticmethod(lazy("covnet.mobile.results", "tracks"))
    rebuild = staticmethod(lazy(_REPLAY, "rebuild"))
    visual = staticmethod(lazy(_VISUAL, "Visual"))
    run_messages = staticmethod(lazy(_VISUAL, "run_messages"))

    def episodes(self, cfg: Any) -> list[str]:
        return [str(cfg.solver)]


KIND = Mobile()
