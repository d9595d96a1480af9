"""Temporary: two-view geometry moved to epi_vo.core.geometry; this re-export goes with the layer move."""

from epi_vo.core.geometry import *  # noqa: F403
from epi_vo.core.geometry import __all__  # noqa: F401
