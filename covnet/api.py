"""The Python API under its short name: ``from covnet import api`` (the code is
:mod:`covnet.cli.api`, beside the command line whose commands it mirrors)."""

from __future__ import annotations

import covnet.errors  # noqa: F401  (first: a folder named covnet/ taken for it says so)
from covnet.cli.api import RunResult, SweepResult, load, run, sweep

__all__ = ["RunResult", "SweepResult", "load", "run", "sweep"]
