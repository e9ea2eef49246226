"""What the ``covnet`` commands share: the exit statuses, the one-line messages on stderr, and
loading a command's config with its run options."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from covnet import kinds
from covnet.processes.interrupts import EXIT_INTERRUPTED as EXIT_INTERRUPTED

EXIT_OK, EXIT_FAIL, EXIT_USAGE = 0, 1, 2
EXIT_PIPE = 141
"""The reader of stdout went away (``covnet check CONFIG | head``): 128 + SIGPIPE, the status
of a Unix tool that the closed pipe stopped."""


def _err(msg: str) -> None:
    print(f"covnet: error: {msg}", file=sys.stderr)


def _note(msg: str) -> None:
    print(f"covnet: {msg}", file=sys.stderr)


def _options(args: argparse.Namespace, *names: str) -> dict[str, Any]:
    """The run options among ``names`` that the command line gave."""
    return {n: getattr(args, n, None) for n in names}


def _load(args: argparse.Namespace, *options: str) -> tuple[Any, Any]:
    """``(kind, config)`` of ``args.config`` with the given run ``options`` applied."""
    kind, cfg = kinds.load(args.config)
    return kind, kinds.apply_options(kind, cfg, args.config, **_options(args, *options))


RUN_OPTIONS = ("seed", "metric", "fusion", "solver")
