"""Shared test fixtures: the trace shipped in the repo, and ../shared/data when present."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
#: The small real trace shipped with the repository (tests may always use it).
SHIPPED_TRACE = REPO / "data" / "gsdc2021" / "train" / "2021-04-28-US-MTV-1" / "Pixel4"
#: The larger development data set beside the checkout; tests using it skip when it is absent.
SHARED_DATA = Path(os.environ.get("GNSSFUSE_SHARED_DATA", REPO.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def shipped_trace_dir() -> Path:
    return SHIPPED_TRACE


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data not present at {SHARED_DATA}")
    return SHARED_DATA
