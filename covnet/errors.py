"""The errors that end a command with a readable line instead of a traceback.

- :class:`UsageError`: a mistake in the user's input (an option, a path, a combination that
  cannot work): one line naming the option and what is allowed, exit status 2.
- :class:`UpError`: ``covnet up`` could not bring the network up or it did not finish: exit 1.

A bad config is a :class:`covnet.config.ConfigError` (exit 2), listing every problem.
"""

from __future__ import annotations

__all__ = ["UpError", "UsageError"]


class UsageError(Exception):
    """A mistake in the user's input, reported without a traceback (exit status 2)."""


class UpError(RuntimeError):
    """The network could not be brought up or did not finish."""
