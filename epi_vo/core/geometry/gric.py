"""Model selection by Torr's Geometric Robust Information Criterion (GRIC; P. Torr, "Geometric motion
segmentation and model selection", Phil. Trans. R. Soc. A 356, 1998; also H&Z's bibliography to ch. 11).

Two models of the same correspondences, one a special case of the other (a rotation is a homography with
three of its eight degrees of freedom), are compared on their residuals against the image noise, each model
paying for its parameters: the simpler one is taken unless the general one explains the points by more than
its extra parameters are worth. No threshold in degrees or pixels: the noise sets the scale.
"""

from __future__ import annotations

import math

import numpy as np

from epi_vo.core.geometry.common import F64

# Torr's constants: a correspondence is DATA_DIM numbers (two image points); a residual counts at most
# GRIC_LAMBDA3 x (DATA_DIM - structure dimension) (an outlier costs what a point at the chi-square edge
# does); each parameter costs ln(DATA_DIM x n), each structure dimension ln(DATA_DIM) per point.
DATA_DIM = 4
GRIC_LAMBDA3 = 2.0


def gric(chi2: F64, n_params: int, structure_dim: int) -> float:
    """GRIC of a model whose squared residuals over the noise's variance are ``chi2`` (n,), with
    ``n_params`` parameters and correspondences on a manifold of ``structure_dim`` dimensions (2 for a
    homography or a rotation: each point of one image fixes its match; 3 for E). Smaller is better."""
    n = int(chi2.size)
    rho = np.minimum(chi2, GRIC_LAMBDA3 * (DATA_DIM - structure_dim))
    return float(np.sum(rho)) + math.log(DATA_DIM) * structure_dim * n + math.log(DATA_DIM * max(n, 1)) * n_params


def simpler_explains(chi2_simple: F64, k_simple: int, chi2_general: F64, k_general: int,
                     structure_dim: int = 2) -> bool:
    """The simpler model (``k_simple`` parameters) explains the correspondences as well as the general one
    (``k_general``) by GRIC: its residuals exceed the general model's by less than its fewer parameters
    save. Non-finite residuals (a point the model sends to infinity) count as outliers."""
    cap = GRIC_LAMBDA3 * (DATA_DIM - structure_dim)
    a = np.where(np.isfinite(chi2_simple), chi2_simple, cap)
    b = np.where(np.isfinite(chi2_general), chi2_general, cap)
    return gric(a, k_simple, structure_dim) <= gric(b, k_general, structure_dim)
