"""The hand-over to a new map: what the camera may have done while no map was behind its pose.

When tracking restarts (lost, a reset, a jump back in time, a new camera_info), the new map starts at
the last pose that had a map behind it (the "good" pose), held. The camera moved on while nothing
measured it, so the new map's pose covariance is the good pose's plus every motion that was possible in
the time without a map (the gap, ``T``), bounded by what the platform can do (``VoConfig``; nav2's
max_vel_x, acc_lim_x, max_vel_theta, acc_lim_theta are the same figures):

* rotation: at most ``min(w_max T, |w_last| T + a_w T^2 / 2)`` about any axis (``w_last`` the turn rate
  between the last two good poses, ``w_max`` = ``max_turn_rate_deg_s``, ``a_w`` =
  ``max_turn_accel_deg_s2``), and never more than a half turn;
* position, once the map is metric: the same with ``max_speed_mps``, ``max_accel_mps2`` and the last
  speed. In VO units a speed in metres has no length; there the last speed over ``T`` is one standard
  deviation (the new map assumes that speed for its baseline too).

A motion known only to lie within a bound ``b`` is taken as spread evenly over ``[-b, b]`` on each axis:
variance ``b^2 / 3``, so a pose that did move by the whole bound is still inside 3 sigma (a normalised
error of 3 on each axis). The gap is the time since the good pose: the frames of a blackout and those
a new map then needs to initialise both count.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from epi_vo.core.config import VoConfig
from epi_vo.core.transforms import rotation_angle_deg

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class GoodPose:
    """The last pose with a map behind it (tracking): stamp, ``T_w_c`` and its covariance."""

    stamp_ns: int
    T_w_c: F64
    cov_w_c: F64


def bounded_motion_var(last_rate: float, max_rate: float, max_accel: float, gap_s: float, cap: float) -> float:
    """Per-axis variance of a motion over ``gap_s`` seconds from ``last_rate``, with the rate at most
    ``max_rate`` and changing by at most ``max_accel`` per second (and the motion at most ``cap``): spread
    evenly over its bound ``b``, ``b^2 / 3``."""
    gap_s = max(gap_s, 0.0)
    b = min(max_rate * gap_s, abs(last_rate) * gap_s + 0.5 * max_accel * gap_s * gap_s, cap)
    return b * b / 3.0


@dataclass(frozen=True)
class Handover:
    """The good pose and the rates there; gives the covariance a new map starts from. Frozen: ``booked``
    returns the hand-over after a pose."""

    speed_limits: tuple[float, float]  # (max speed m/s, max acceleration m/s^2)
    turn_limits: tuple[float, float]  # (max turn rate rad/s, max angular acceleration rad/s^2)
    lost_position_variance: float
    good: GoodPose | None = None
    rates: tuple[float, float] = (0.0, 0.0)  # (map units / s, rad / s) between the last two good poses

    @staticmethod
    def from_config(cfg: VoConfig) -> Handover:
        return Handover((cfg.max_speed_mps, cfg.max_accel_mps2),
                        (math.radians(cfg.max_turn_rate_deg_s), math.radians(cfg.max_turn_accel_deg_s2)),
                        cfg.lost_position_variance)

    def booked(self, stamp_ns: int, T_w_c: F64, cov_w_c: F64) -> Handover:
        """This frame's pose has a map behind it: the hand-over remembering it (and the camera's rates)."""
        good, rates = self.good, self.rates
        if good is not None and stamp_ns > good.stamp_ns:
            dt = (stamp_ns - good.stamp_ns) * 1e-9
            step = float(np.linalg.norm(T_w_c[:3, 3] - good.T_w_c[:3, 3]))
            turn = math.radians(rotation_angle_deg(good.T_w_c[:3, :3].T @ T_w_c[:3, :3]))
            rates = (step / dt, turn / dt)
        return dataclasses.replace(self, good=GoodPose(int(stamp_ns), T_w_c.copy(), cov_w_c.copy()), rates=rates)

    def covariance(self, stamp_ns: int, metric: bool, scale_cov: F64 | None = None) -> F64 | None:
        """Covariance of the held pose a new map starts from at ``stamp_ns``: the good pose's, its map's
        scale error ``scale_cov`` (3x3 position, metric maps), and the motion possible since (module doc).
        None before any good pose."""
        good = self.good
        if good is None:
            return None
        gap_s = max((stamp_ns - good.stamp_ns) * 1e-9, 0.0)
        speed, turn_rate = self.rates
        cov = good.cov_w_c.copy()
        if scale_cov is not None:
            cov[:3, :3] += scale_cov
        if metric:
            pos_var = bounded_motion_var(speed, *self.speed_limits, gap_s, math.sqrt(3.0 * self.lost_position_variance))
        else:
            pos_var = (speed * gap_s) ** 2
        cov[:3, :3] += np.eye(3) * pos_var
        cov[3:, 3:] += np.eye(3) * bounded_motion_var(turn_rate, *self.turn_limits, gap_s, math.pi)
        return cov


@dataclass(frozen=True)
class HeldStart:
    """The position held without a map since ``since_ns`` (initialising, after a restart), and what the
    images measured of the camera's motion meanwhile, in parallax: the median parallax of the tracks
    against the reference keyframe (rotation taken out) grows with the camera's displacement over the
    scene's depth. Each reference given up while held books the parallax last measured against it; the
    time after that frame, until the next reference, is blind: there the motion is taken at the speeds
    measured on either side (the last parallax rate before, the new map's first speed after), changing
    evenly in between (constant acceleration)."""

    since_ns: int
    ref_ns: int  # the current reference keyframe's stamp
    parallax_deg: float = 0.0  # booked: measured against the references given up
    blind_s: float = 0.0  # booked: time with no frame measured against a reference
    blind_deg: float = 0.0  # booked: the parallax rate before each blind time, times that time
    seen_deg: float = 0.0  # the last parallax measured against the current reference
    seen_ns: int | None = None  # and its frame's stamp (None: nothing measured against it yet)
    rate_deg_s: float = 0.0  # the last parallax rate measured (deg / s)

    @staticmethod
    def at(stamp_ns: int) -> HeldStart:
        return HeldStart(int(stamp_ns), int(stamp_ns))

    def seen(self, stamp_ns: int, parallax_deg: float) -> HeldStart:
        """A frame measured against the current reference with this median parallax."""
        if not math.isfinite(parallax_deg) or stamp_ns <= self.ref_ns:
            return self
        return dataclasses.replace(self, seen_deg=float(parallax_deg), seen_ns=int(stamp_ns),
                                   rate_deg_s=float(parallax_deg) / ((stamp_ns - self.ref_ns) * 1e-9))

    def reanchored(self, stamp_ns: int) -> HeldStart:
        """The reference moves to the frame at ``stamp_ns``: what was seen against the old one is booked,
        and the time since the last frame measured against it is blind."""
        last = self.ref_ns if self.seen_ns is None else self.seen_ns
        blind = max(stamp_ns - last, 0) * 1e-9
        return HeldStart(self.since_ns, int(stamp_ns), self.parallax_deg + self.seen_deg, self.blind_s + blind,
                         self.blind_deg + self.rate_deg_s * blind, rate_deg_s=self.rate_deg_s)

    def motion_var(self, baseline: float, baseline_s: float, parallax_deg: float) -> float:
        """Per-axis position variance of the motion while held, for a new map whose first baseline is
        ``baseline`` map units in ``baseline_s`` seconds at ``parallax_deg`` median parallax: the new map's
        baseline per degree of parallax turns what was seen into map units (the same scene), the blind time
        moves at the mean of the speeds before and after it, and the displacement ``d``, known in norm
        only, is spread over the axes (``d^2 / 3``). Without the new map's parallax, its first speed over
        the whole held time is one standard deviation (the hand-over in VO units)."""
        if baseline_s <= 0.0 or not math.isfinite(baseline):
            return 0.0
        speed = baseline / baseline_s
        if not (math.isfinite(parallax_deg) and parallax_deg > 0.0):
            return (speed * max((self.ref_ns - self.since_ns) * 1e-9, 0.0)) ** 2
        per_deg = baseline / parallax_deg
        d = per_deg * (self.parallax_deg + 0.5 * self.blind_deg) + 0.5 * speed * self.blind_s
        return d * d / 3.0
