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


QUOTE_MAX_CHARS = 60  # of a value quoted from a message into an error: enough to recognise it, and bounded,
# since the error becomes the reason of every frame's record and status (a 1 MB encoding string would
# otherwise be copied into each of them)


def clipped(text: str, limit: int = QUOTE_MAX_CHARS) -> str:
    """``text`` cut to ``limit`` characters, with its full length said when it was cut."""
    return text if len(text) <= limit else f"{text[:limit]}… ({len(text)} characters)"


def quoted(value: object, limit: int = QUOTE_MAX_CHARS) -> str:
    """``repr(value)`` for an error message, cut to about ``limit`` characters with the full length said
    ("'xxxx…' (1048576 characters)"). Sequences (lists, arrays) show their first items and their length."""
    if isinstance(value, str):
        if len(value) <= limit:
            return repr(value)
        return f"{value[:limit]!r}… ({len(value)} characters)"
    if isinstance(value, list | tuple) and len(value) > 8:
        return f"{list(value[:8])!r}… ({len(value)} values)"
    return clipped(repr(value), limit)
