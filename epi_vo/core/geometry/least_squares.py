"""Levenberg-Marquardt over a small parameter vector (H&Z A6.2): the loop the model refits share
(``epipolar_refine.refine_relative_pose``, ``models._refine_homography``). The model supplies its
linearisation at the current estimate and how a step moves it (a rotation on its manifold, a direction in
its tangent plane, a matrix's entries); the loop decides the damping and when to stop.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Generic, TypeVar, cast

import numpy as np

from epi_vo.core.geometry.common import F64

S = TypeVar("S")

# The damping starts small (Gauss-Newton from a good start, which every caller has), is divided by ten after a
# step that lowers the cost and multiplied by ten after one that does not; past LM_MAX_DAMPING no step along the
# gradient lowers the cost at the precision of float64 and the estimate is final.
LM_START_DAMPING = 1e-3
LM_MAX_DAMPING = 1e8
# Damping is relative to the normal equations' diagonal: at a billionth the step is Gauss-Newton's, and a lower
# floor would only cost more rejected steps to climb back when the cost stops falling.
LM_MIN_DAMPING = 1e-9
# A step that lowers the cost by less than this fraction ends the search: the remaining gain is below the
# residuals' rounding.
LM_RELATIVE_DECREASE = 1e-10


class Linearised(Generic[S]):
    """The residuals ``r`` and Jacobian ``J`` at an estimate, and ``move(step)``: the estimate after a step."""

    def __init__(self, r: F64, J: F64, move: Callable[[F64], S]) -> None:
        self.r, self.J, self.move = r, J, move


def levenberg_marquardt(x0: S, linearise: Callable[[S], Linearised[S]], residuals: Callable[[S], F64],
                        iterations: int) -> tuple[S, float, float]:
    """Minimise ``|residuals(x)|^2`` from ``x0``; returns ``(x, cost at x0, cost at x)``. Each iteration
    linearises once and tries steps of growing damping until one lowers the cost (a non-finite cost never
    does)."""
    x = x0
    r0 = residuals(x0)
    cost0 = cost = float(r0 @ r0)
    lam = LM_START_DAMPING
    for _ in range(iterations):
        lin = linearise(x)
        A, g = lin.J.T @ lin.J, lin.J.T @ lin.r
        done = False
        while lam < LM_MAX_DAMPING:
            step = cast(F64, np.linalg.solve(A + lam * np.diag(np.diag(A) + 1e-18), -g))
            x1 = lin.move(step)
            r1 = residuals(x1)
            c1 = float(r1 @ r1)
            if math.isfinite(c1) and c1 < cost:
                done = cost - c1 < LM_RELATIVE_DECREASE * cost
                x, cost, lam = x1, c1, max(lam / 10.0, LM_MIN_DAMPING)
                break
            lam *= 10.0
        else:
            break
        if done:
            break
    return x, cost0, cost
