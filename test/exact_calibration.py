"""The bundled bags' CameraInfo is their renderer's exact camera. The defaults' calibration uncertainty
(``principal_point_sigma_px``, ``focal_length_rel_sigma``, ``radial_distortion_k1_sigma``: a real camera's,
``core.calibration_cov``) would make their covariance cautious; a test that judges another covariance term's
consistency on them declares the calibration exact."""

from __future__ import annotations

import dataclasses

from epi_vo.core.config import VoConfig

EXACT_CALIBRATION = {"principal_point_sigma_px": 0.0, "focal_length_rel_sigma": 0.0, "radial_distortion_k1_sigma": 0.0}


def exact(cfg: VoConfig | None = None, **values: object) -> VoConfig:
    """``cfg`` (default: the defaults) with ``values`` and the calibration declared exact."""
    return dataclasses.replace(cfg or VoConfig(), **EXACT_CALIBRATION, **values)  # type: ignore[arg-type]
