"""Fixtures for multi-process tests (helpers live in ``multiproc.py``)."""

from __future__ import annotations

import pytest
from multiproc import CovnetProcess


@pytest.fixture()
def covnet_proc():
    started: list[CovnetProcess] = []

    def start(args: list[str]) -> CovnetProcess:
        p = CovnetProcess(args)
        started.append(p)
        return p

    yield start
    for p in started:
        p.stop()
