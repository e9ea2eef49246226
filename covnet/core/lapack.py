"""scipy's LAPACK routines without importing ``scipy.linalg`` (start-up time).

``import scipy.linalg`` runs the package's ``__init__``, which imports its whole API and, through
``scipy._lib._array_api``, clones numpy's namespace (loading ``numpy.f2py``, ``numpy.ma``,
``numpy.testing``, ...): 0.15 to 0.45 s of a process's start, more than everything else covnet
imports.  The routines the core calls (``dpotrf``, ``dpotrs``, ``dpotri``, ``dsyev``) live in one
f2py extension, ``scipy.linalg._flapack``, which needs numpy only.  :func:`flapack` loads that
extension from scipy's own folder, registered under its own name in ``sys.modules``, so a later
``import scipy.linalg`` reuses the very same module (the same functions, hence the same bits as
``scipy.linalg.lapack.dpotrf`` & co: a test checks it).  If scipy does not have the file where
it keeps it, :func:`flapack` imports ``scipy.linalg.lapack`` the ordinary way.
"""

from __future__ import annotations

import importlib.util
import sys
import threading
from pathlib import Path
from types import ModuleType

__all__ = ["flapack"]

_NAME = "scipy.linalg._flapack"
_lock = threading.Lock()
_module: ModuleType | None = None


def flapack() -> ModuleType:
    """The module of scipy's double-precision LAPACK wrappers (``dpotrf``, ``dpotrs``, ...)."""
    global _module
    if _module is not None:
        return _module
    with _lock:
        if _module is None:
            _module = _load()
    return _module


def _load() -> ModuleType:
    loaded = sys.modules.get(_NAME)
    if loaded is not None:
        return loaded
    try:
        import scipy  # the package's own __init__ is light (start-up: the point of this module)

        folder = Path(scipy.__file__).parent / "linalg"
        files = sorted(folder.glob("_flapack.*.so")) + sorted(folder.glob("_flapack.*.pyd"))
        spec = importlib.util.spec_from_file_location(_NAME, files[0]) if files else None
        if spec is None or spec.loader is None:
            raise ImportError(f"no {_NAME} extension in {folder}")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        module.dpotrf  # noqa: B018 (the routines are there: else the ordinary import)
    except (ImportError, OSError, AttributeError, IndexError):
        from scipy.linalg import lapack  # start-up: only when the fast path is not available

        return lapack
    sys.modules[_NAME] = module
    return module
