"""Which code wrote a result: a digest of covnet's own source.

``covnet.__version__`` names a release, and results change between commits of one release
(a fix in the last bits of a covariance, a field counted differently).  So whatever a later
covnet reads back as its own — a batch's finished trials that a resume skips, a recording
that ``covnet replay`` re-fuses — carries :func:`code_identity`: the SHA-256 (16 hex digits) of
every ``.py`` file of covnet's packages, each named by its path below the packages' root, in
sorted order.  The same source gives the same identity on every host and install (editable
or a wheel); any change to the source gives another.  Hidden files (an editor's lock file
``.#config.py``) are left out, and a file that cannot be read counts by its error: the
identity never fails a command.  A resumed batch runs again the trials of
other code (:mod:`covnet.batches.trials`); a replay names the code that recorded the run when
it is not its own (:mod:`covnet.runs.replay_kit`)."""

from __future__ import annotations

import functools
from pathlib import Path

__all__ = ["PACKAGES", "code_identity", "other_code", "packages_root"]

PACKAGES = ("covnet", "manager", "sensors", "world", "recorder")
"""The top-level packages of covnet (pyproject's ``packages.find``)."""


def packages_root() -> Path:
    """The folder that holds :data:`PACKAGES` (the clone, or ``site-packages`` for a wheel):
    what the identity reads, and where the launcher and the nodes take covnet's node packages
    from rather than the working directory's."""
    return Path(__file__).resolve().parents[1]


@functools.cache
def code_identity() -> str:
    """The digest of this process's covnet source (read once: the modules a process runs are
    the ones it imported)."""
    import hashlib  # start-up: not before the command's signal handlers (covnet/__main__)

    root = packages_root()
    h = hashlib.sha256()
    for pkg in PACKAGES:
        for path in sorted((root / pkg).rglob("*.py")):
            rel = path.relative_to(root)
            if any(part.startswith(".") for part in rel.parts):
                continue  # an editor's lock or backup (.#config.py), never imported
            try:
                data = path.read_bytes()
            except OSError as exc:  # a file Python could not import either: named, not fatal
                data = f"<unreadable: {exc.strerror}>".encode()
            h.update(rel.as_posix().encode() + b"\0")
            h.update(data + b"\0")
    return h.hexdigest()[:16]


def other_code(recorded: object) -> str | None:
    """``None`` when ``recorded`` (a file's ``code``) is this code's identity, else a phrase
    naming the code that wrote it (``another covnet's (<id>)``, or an older covnet's, which
    wrote none)."""
    if recorded == code_identity():
        return None
    if isinstance(recorded, str) and recorded:
        return f"another covnet's ({recorded}; this one is {code_identity()})"
    return f"an older covnet's (it names no code; this one is {code_identity()})"
