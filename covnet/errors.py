"""The errors that end a command with a readable line instead of a traceback.

- :class:`UsageError`: a mistake in the user's input (an option, a path, a combination that
  cannot work): one line naming the option and what is allowed, exit status 2.
- :class:`UpError`: ``covnet up`` could not bring the network up or it did not finish: exit 1.
- :class:`WorkerDied`: a batch's worker process ended without its task's result (killed, out
  of memory): that task failed, the others went on; exit 1.
- :class:`ClusterLost`: the Dask scheduler of a ``--cluster`` batch went away: the tasks not
  finished failed (the finished trials are saved); exit 1.

A bad config is a :class:`covnet.config.ConfigError` (exit 2), listing every problem.

Importing this module checks that ``covnet`` is this package: from the folder that holds a
clone of the repository named ``covnet/``, Python takes that folder (it has no
``__init__.py``) for ``covnet``, a namespace package, while an editable install still finds
the modules; the first ``from covnet import __version__`` would then fail with a message that
does not say why.  The entry points (:mod:`covnet.cli.api`, :mod:`covnet.cli.app`) import this
module
first, so the :class:`ImportError` says what is wrong and how to avoid it.
"""

from __future__ import annotations

import sys

__all__ = ["ClusterLost", "NoRun", "UpError", "UsageError", "WorkerDied", "shadowed_package"]


def shadowed_package() -> str | None:
    """Why ``covnet`` is not this package (None: it is)."""
    package = sys.modules.get("covnet")
    if package is None or getattr(package, "__file__", None) is not None:
        return None
    folders = ", ".join(str(p) for p in getattr(package, "__path__", [])) or "a folder"
    return (
        f"'covnet' is not the covnet package here: Python took the folder {folders} for it "
        "(a folder without __init__.py is a namespace package, and the current directory "
        "comes first on sys.path). This happens in the folder that holds a clone of the "
        "repository named covnet/: run Python from inside the clone or any other folder, or "
        "rename the clone's folder"
    )


if (_problem := shadowed_package()) is not None:
    raise ImportError(_problem)


class UsageError(Exception):
    """A mistake in the user's input, reported without a traceback (exit status 2)."""


class UpError(RuntimeError):
    """The network could not be brought up or did not finish."""


class NoRun(ConnectionError):
    """A node found no run to join: its session with the run's router did not open (nothing
    listens there, or the router refuses it), or no manager of its run appeared in time.  Its
    process exits :data:`covnet.processes.launch.EXIT_NO_RUN` and is not restarted: trying
    again cannot make the run appear (``restart: on-failure`` on a sensors-only host restarted
    such a sensor every half minute, without end)."""


class WorkerDied(RuntimeError):
    """A worker process ended without sending its task's result (killed, out of memory): a
    failure of that task, the others go on (on a new worker)."""


class ClusterLost(RuntimeError):
    """The Dask scheduler a batch ran on went away (its client closed): every task not
    finished is a failure of this kind."""
