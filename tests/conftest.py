"""Shared fixtures and the hypothesis profile used by every test layer."""

from __future__ import annotations

import contextlib
import os
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

import covnet  # noqa: F401  (first: pins OpenBLAS's kernels before any test imports NumPy)

settings.register_profile(
    "ci",
    derandomize=True,
    deadline=None,
    max_examples=60,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.load_profile("ci")

REPO = Path(__file__).resolve().parents[1]
PAPER = REPO / "configs" / "paper.yaml"


@pytest.fixture(scope="session")
def paper_path() -> Path:
    return PAPER


@pytest.fixture(scope="session")
def paper():
    from covnet.covariance_control.config import load

    return load(PAPER)


class SignalFromAnotherThread(Exception):
    """Raised by the SIGUSR1 handler of :func:`interrupted_from_another_thread`."""


@pytest.fixture
def interrupted_from_another_thread():
    """``check(blocking_call)``: runs ``blocking_call()`` in the main thread while another
    thread, 0.3 s later, takes a SIGUSR1 whose handler raises; returns the seconds until the
    call was interrupted (the kernel may hand a process signal to any thread, and Python runs
    the handler in the main thread only between bytecodes)."""
    import signal
    import threading
    import time

    def check(blocking_call) -> float:
        assert threading.current_thread() is threading.main_thread()
        release = threading.Event()

        def idle():
            if not release.wait(0.3):  # the main thread is blocked by now
                signal.pthread_kill(threading.get_ident(), signal.SIGUSR1)
            release.wait(30)

        def handler(signum, frame):
            raise SignalFromAnotherThread

        other = threading.Thread(target=idle)
        old = signal.signal(signal.SIGUSR1, handler)
        try:
            t0 = time.monotonic()
            other.start()
            with pytest.raises(SignalFromAnotherThread):
                blocking_call()
            return time.monotonic() - t0
        finally:
            release.set()
            other.join(10)
            signal.signal(signal.SIGUSR1, old)

    return check


@pytest.fixture(scope="module")
def room_in_the_names_cache():
    """An empty cache of ids seen valid (``covnet.wire.keys._GOOD_NAMES``) for the module, its
    contents restored after: the fast and batch decoders take only ids in it, and the strict
    path adds no more once it holds ``_GOOD_NAMES_MAX`` (a long test process fills it)."""
    from covnet.wire.keys import _GOOD_NAMES

    saved = set(_GOOD_NAMES)
    _GOOD_NAMES.clear()
    yield
    _GOOD_NAMES.clear()
    _GOOD_NAMES.update(saved)


@contextlib.contextmanager
def _tmpfs(where: Path, options: str) -> Iterator[Path]:
    where.mkdir()
    r = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(where)],
        capture_output=True,
        text=True,
        check=False,
    )
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({r.stderr.strip() or r.returncode})")
    try:
        yield where
    finally:
        subprocess.run(["umount", str(where)], check=True)


@pytest.fixture
def tmpfs(tmp_path) -> Iterator:
    """``tmpfs(name, options)``: a tmpfs mounted at ``tmp_path / name`` with the mount
    ``options`` (``size=100k``, ``ro``), unmounted after the test; the test is skipped without
    root or where a tmpfs cannot be mounted (real full and read-only file systems)."""
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root")
    with contextlib.ExitStack() as stack:

        def mount(name: str, options: str) -> Path:
            return stack.enter_context(_tmpfs(tmp_path / name, options))

        yield mount


@pytest.fixture
def saved_figures(monkeypatch):
    """``keep(module)``: from then on the figures ``module`` saves (its ``save_figure``) are
    also appended to the returned list, still open, for a test to read what was drawn."""
    figs: list = []

    def keep(module):
        real = module.save_figure

        def save(fig, path, **kw):
            figs.append(fig)
            real(fig, path, **kw)

        monkeypatch.setattr(module, "save_figure", save)
        return figs

    return keep
