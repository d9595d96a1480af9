"""Fixtures shared by the tools' tests."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="session")
def make_bags() -> object:
    """``bags/make_bags.py`` (the bag renderer) as a module; skipped without scikit-image."""
    pytest.importorskip("skimage", reason="bags/make_bags.py needs scikit-image (bags/requirements.txt)")
    sys.path.insert(0, str(REPO / "bags"))
    try:
        import make_bags
    finally:
        sys.path.remove(str(REPO / "bags"))
    return make_bags
