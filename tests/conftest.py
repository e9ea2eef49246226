"""Shared fixtures and the hypothesis profile used by every test layer."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

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
    from covnet.config import load

    return load(PAPER)
