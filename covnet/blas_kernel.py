"""One BLAS kernel on every x86-64 machine, so that a config and a seed give the same bits
everywhere.

NumPy's and SciPy's wheels ship OpenBLAS built with ``DYNAMIC_ARCH``: at load time it picks the
kernels for the CPU it finds (``Haswell`` on an AVX2 machine, ``SkylakeX`` or ``Cooperlake``
where AVX-512 is there, ...).  The kernels round differently, so the same run gives different
last bits on two machines, and over 100 scans of a filter and an argmin over subsets those bits
can change a decision: the paper run's ``summary.json`` differs between an AVX2 and an AVX-512
host (measured: the golden hashes of ``tests/golden`` were recorded on one, CI ran on the
other).  Reproducibility across processes, hosts and cluster workers is a promise of covnet, so
:func:`pin` asks OpenBLAS for the ``Haswell`` kernels (AVX2 + FMA: every x86-64 server of the
last decade) through ``OPENBLAS_CORETYPE``, which OpenBLAS reads when it is loaded.

That works only before NumPy is imported, which is why ``covnet/__init__.py`` calls it first
thing; the processes covnet starts inherit the variable.  A user's own setting of
``OPENBLAS_CORETYPE`` is kept.  A CPU without AVX2/FMA, a machine that is not x86-64, and a
NumPy imported before covnet keep OpenBLAS's own choice; :func:`kernel` says which kernel a
process really runs (``run.json`` records it), so a difference can be traced.
"""

from __future__ import annotations

import ctypes
import os
import sys
from pathlib import Path

__all__ = ["PINNED", "kernel", "one_thread", "pin"]

PINNED = "Haswell"
"""The OpenBLAS kernel set covnet asks for on x86-64 (needs AVX2 and FMA)."""
_NEEDS = frozenset({"avx2", "fma"})


def _cpu_flags() -> frozenset[str]:
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return frozenset()
    for line in text.splitlines():
        if line.startswith("flags"):
            return frozenset(line.partition(":")[2].split())
    return frozenset()


def _machine() -> str:
    """The CPU architecture, lower case (``os.uname``: ``platform`` costs milliseconds)."""
    if hasattr(os, "uname"):
        return os.uname().machine.lower()
    return os.environ.get("PROCESSOR_ARCHITECTURE", "").lower()


def one_thread() -> None:
    """Ask OpenBLAS for one thread (``OPENBLAS_NUM_THREADS=1``) unless the user set a number or
    NumPy is already loaded.  covnet's matrices are 2 x 2 to 6 x 6 (a thread pool never pays on
    them) and it runs many processes at once (every sensor, the batch workers), so a pool per
    process only costs: its start-up is about a third of NumPy's import time (``covnet run``'s
    start-up), and with dozens of processes on a few cores the pools' spinning threads contend.
    OpenBLAS computes each output element in one thread, in the same order, whatever the
    number of threads: the results are the same bits."""
    if "numpy" not in sys.modules:
        os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def pin() -> bool:
    """Set ``OPENBLAS_CORETYPE`` to :data:`PINNED` when it can still take effect (NumPy not yet
    imported, not set by the user, an x86-64 CPU with AVX2 and FMA); True if it is in force."""
    if "OPENBLAS_CORETYPE" in os.environ:
        return os.environ["OPENBLAS_CORETYPE"] == PINNED
    if "numpy" in sys.modules or _machine() not in ("x86_64", "amd64"):
        return False
    if not _NEEDS <= _cpu_flags():
        return False
    os.environ["OPENBLAS_CORETYPE"] = PINNED
    return True


def kernel() -> str | None:
    """The kernel set NumPy's OpenBLAS runs in this process (``"Haswell"``, ``"SkylakeX"``,
    ...), or None where it cannot be asked (another BLAS, another layout of the wheel)."""
    import numpy as np  # here, not at module level: at start-up pin() runs before NumPy loads

    libs = Path(np.__file__).parent.parent / "numpy.libs"
    for lib in sorted(libs.glob("libscipy_openblas*.so*")):
        try:
            handle = ctypes.CDLL(str(lib))
        except OSError:
            continue
        for name in ("scipy_openblas_get_corename64_", "scipy_openblas_get_corename"):
            fn = getattr(handle, name, None)
            if fn is not None:
                fn.restype = ctypes.c_char_p
                value = fn()
                return value.decode().strip() if value else None
    return None
