"""The ``passive`` kind (fast association of angle-only measurements from three passive
sensors, issue 6): what the kind registry (:mod:`covnet.kinds`) knows of it.

Process roles: ``manager.passive``, ``sensors.passive``, ``world.passive``.  Run option:
``--seed`` (a change of the config).  Commands (in :mod:`covnet.passive.commands`):
``covnet mc`` (the §9 protocol) and ``covnet bench passive``; ``covnet replay`` and the rebuild
of a network run from its recording are :mod:`covnet.passive.replay`'s.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from covnet.errors import UsageError
from covnet.kindkit import KindBase, lazy, seed_option
from covnet.passive import config

__all__ = ["KIND"]

_COMMANDS = "covnet.passive.commands"
_VISUAL = "covnet.passive.visual"
_REPLAY = "covnet.passive.replay"


class Passive(KindBase):
    config = config
    name = config.KIND
    title = "passive"
    roles = {"manager": "manager.passive", "sensor": "sensors.passive", "world": "world.passive"}
    options = {"seed": seed_option}
    commands = {
        "mc": lazy(_COMMANDS, "mc"),
        "replay": lazy(_REPLAY, "command"),
        "bench:passive": lazy(_COMMANDS, "bench"),
    }
    run = staticmethod(lazy(_COMMANDS, "run"))
    after_up = staticmethod(lazy(_COMMANDS, "after_up"))
    plot = staticmethod(lazy(_COMMANDS, "plot"))
    rebuild = staticmethod(lazy(_REPLAY, "rebuild"))
    visual = staticmethod(lazy(_VISUAL, "Visual"))
    run_messages = staticmethod(lazy(_VISUAL, "run_messages"))

    def episodes(self, cfg: Any) -> list[str]:
        return [str(cfg.association.method)]

    def tracks(self, cfg: Any, run_dir: Path) -> list[Any]:
        raise UsageError(
            f"{run_dir}: a passive run holds one association scene (each sensor's directions, "
            "the triples chosen and the targets' fixed positions), no truths and tracks over "
            "time: nothing to export"
        )


KIND = Passive()
