"""Project exceptions: one root, one subclass per area (evo / rosbags style).

Bad input or misuse raises one of these with a message naming the problem. Expected outcomes of the
geometry (too few matches, pure rotation, planar scene, low parallax, tracking lost) are never
exceptions: they are values in the frame result.
"""

from __future__ import annotations


class EpiVoError(Exception):
    """Root of every error epi_vo raises on purpose."""


class ConfigError(EpiVoError):
    """Invalid configuration values; the message lists every bad field at once."""


class CameraModelError(EpiVoError):
    """Calibration that cannot be used: uncalibrated K, non-finite values, unknown model, size mismatch."""


class ImageConversionError(EpiVoError, TypeError):
    """An image message that cannot be turned into an array (encoding, step, size, corrupt data)."""


class BagError(EpiVoError):
    """A bag that cannot be read as asked: missing file, no image topic, ambiguous topics, bad storage."""


class EvaluationError(EpiVoError):
    """Trajectories that cannot be evaluated: bad shapes, non-finite values, too few matched poses."""


class ReportError(EpiVoError):
    """A replay output directory a report cannot be made from (missing or malformed files)."""


class OutputError(EpiVoError):
    """An output path that cannot be created or written (an existing file, a path under a file, no
    permission, disk full)."""


class Interrupted(KeyboardInterrupt):
    """A signal (SIGINT, SIGTERM, SIGHUP) stopped a run at a safe point, its outputs finalised.

    A KeyboardInterrupt, so code that handles Ctrl-C handles it; ``signum`` says which signal it was
    (the command line exits 129 for SIGHUP, 130 for the others).
    """

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum
