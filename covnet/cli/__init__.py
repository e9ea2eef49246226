"""The command line and the Python API: :mod:`covnet.cli.app` (``covnet ...``, argparse) and
:mod:`covnet.cli.api` (``run()``, ``sweep()``, result objects)."""

from __future__ import annotations

from collections.abc import Sequence


def main(argv: Sequence[str] | None = None) -> int:
    """``covnet``'s entry point (the console script ``covnet.cli:main``):
    :func:`covnet.cli.app.main`, imported when called (start-up: importing the API does not
    load the parser)."""
    from covnet.cli.app import main as app_main

    return app_main(argv)
