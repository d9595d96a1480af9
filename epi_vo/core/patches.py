"""Affine patch refinement: each KLT track measured against its patch in the image it was first seen in.

Pyramidal Lucas-Kanade chains each track from the previous frame with a translation-only window. As the
camera moves, a patch scales and shears; LK then locks onto a slightly different point each frame, and
the errors add up along the track. Measured on ground_robot against the renderer's depth (corners of
four keyframes, followed 12 frames): the chained position drifts 0.12, 0.28, 0.41, 0.55, 0.64, 0.72 px
(median) after 1, 3, 5, 7, 10, 12 frames, with a lag-1 autocorrelation of 0.8 along a track, so the
windowed adjustment's observations do not average out.

``PatchTemplates`` (a frozen value the tracking state holds) keeps every track's template from its first
image and, each frame, moves the KLT
position to where an affine warp of that template fits best (inverse-compositional Gauss-Newton,
Baker & Matthews 2004, with a bias and gain per patch and Gaussian weights, on all tracks at once: one
``cv2.remap`` per iteration). The same measurement with 15 px patches and two iterations: 0.06, 0.08,
0.09, 0.12, 0.14, 0.16 px. A fit that lands far from the KLT position, correlates poorly or degenerates
keeps the KLT position, and that track's template starts again from the current image; so does one
whose patch has grown or shrunk by a third (the template's pixels no longer stand for the view's).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np
from numpy.typing import NDArray

from epi_vo.core.config import Frontend, VoConfig

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]

REFINE_ITERATIONS = 2  # Gauss-Newton steps (seeded by KLT and the last warp; four gave 0.002-0.02 px less drift)
REFINE_STOP_PX = 0.02  # all updates below this: converged (a tenth of the drift the refinement removes per frame)
REFINE_MAX_SHIFT_PX = 2.0  # a fit farther than this from the KLT position is not the same point
# The fitted patch must correlate this well with its template (normalised cross-correlation, gain and bias
# taken out): below, the patch no longer shows the template's texture (occlusion, a specular change).
REFINE_MIN_NCC = 0.8
# sqrt(det A) outside this range: the patch grew or shrank by a third, its template's pixels no longer stand
# for the view's, and the template is taken again from this image.
REFINE_SCALE_RANGE = (0.75, 1.33)
# The warp's singular values this far apart: a patch seen this obliquely is a different texture, not the
# template affinely moved.
REFINE_MAX_ANISOTROPY = 2.0


def _grid(patch_px: int, margin: int = 0) -> tuple[F32, F32]:
    r = patch_px // 2 + margin
    g = np.arange(-r, r + 1, dtype=np.float32)
    gx, gy = np.meshgrid(g, g)
    return gx.ravel(), gy.ravel()


def _sample(img: F32, t: F64, A: F64, ox: F32, oy: F32) -> F32:
    """Bilinear samples (N, M) of ``img`` at ``t + A @ (ox, oy)`` for every row."""
    tf, Af = t.astype(np.float32), A.astype(np.float32)
    mx = tf[:, 0, None] + Af[:, 0, 0, None] * ox + Af[:, 0, 1, None] * oy
    my = tf[:, 1, None] + Af[:, 1, 0, None] * ox + Af[:, 1, 1, None] * oy
    return cast(F32, cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE))


def _singular_values(A: F64) -> tuple[F64, F64]:
    """Largest and smallest singular values of each 2x2 ``A`` (N, 2, 2), in closed form."""
    a = A[:, 0, 0] ** 2 + A[:, 1, 0] ** 2
    d = A[:, 0, 1] ** 2 + A[:, 1, 1] ** 2
    b = A[:, 0, 0] * A[:, 0, 1] + A[:, 1, 0] * A[:, 1, 1]
    half, disc = 0.5 * (a + d), np.sqrt(np.maximum(0.25 * (a - d) ** 2 + b * b, 0.0))
    return np.sqrt(half + disc), np.sqrt(np.maximum(half - disc, 0.0))


@dataclass(frozen=True)
class PatchGrid:
    """The sampling grid of one patch size: offsets, Gaussian weights, and the grid with a margin."""

    patch_px: int
    ox: F32
    oy: F32
    w: F32
    mx: F32  # with a 1 px margin for the template's gradient
    my: F32

    @staticmethod
    def of(patch_px: int) -> PatchGrid:
        if patch_px < 5 or patch_px % 2 == 0:
            raise ValueError(f"patch_px={patch_px}: must be odd and at least 5")
        ox, oy = _grid(patch_px)
        sigma = (patch_px // 2) / 1.5
        w = np.exp(-(ox**2 + oy**2) / (2.0 * sigma * sigma)).astype(np.float32)
        mx, my = _grid(patch_px, 1)
        return PatchGrid(patch_px, ox, oy, w, mx, my)


@dataclass(frozen=True)
class PatchTemplates:
    """Templates of the live tracks (by track id) and the affine warp of each into the latest image.

    Frozen: ``anchored`` and ``refined`` return the templates after the keyframe or the frame."""

    grid: PatchGrid
    ids: NDArray[np.int64]  # sorted
    tm: F32  # (n, m) zero-mean template
    tss: F32  # its sum of squares
    sdw: F32  # (n, 6, m) weighted steepest-descent images
    hinv: F32  # (n, 6, 6)
    A: F64  # (n, 2, 2) warp of each template into the latest image

    @staticmethod
    def empty(patch_px: int) -> PatchTemplates:
        grid = PatchGrid.of(patch_px)
        m = patch_px * patch_px
        return PatchTemplates(grid, np.zeros(0, np.int64), np.zeros((0, m), np.float32), np.zeros(0, np.float32),
                              np.zeros((0, 6, m), np.float32), np.zeros((0, 6, 6), np.float32), np.zeros((0, 2, 2)))

    @property
    def patch_px(self) -> int:
        return self.grid.patch_px

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    def _inside(self, shape: tuple[int, ...], t: F64, A: F64 | None = None) -> NDArray[np.bool_]:
        h, w = shape[:2]
        reach = (self.patch_px // 2 + 2) * (1.0 if A is None else np.abs(A).sum(axis=2).max(axis=1))
        return (t[:, 0] >= reach) & (t[:, 0] <= w - 1 - reach) & (t[:, 1] >= reach) & (t[:, 1] <= h - 1 - reach)

    def _templates(self, img: F32, pts: F64) -> tuple[F32, F32, F32, F32]:
        n, p, g = pts.shape[0], self.patch_px, self.grid
        eye = np.broadcast_to(np.eye(2), (n, 2, 2))
        big = _sample(img, pts, eye, g.mx, g.my).reshape(n, p + 2, p + 2)
        t = big[:, 1:-1, 1:-1].reshape(n, -1)
        gx = (0.5 * (big[:, 1:-1, 2:] - big[:, 1:-1, :-2])).reshape(n, -1)
        gy = (0.5 * (big[:, 2:, 1:-1] - big[:, :-2, 1:-1])).reshape(n, -1)
        tm = t - t.mean(axis=1, keepdims=True)
        ox, oy = g.ox, g.oy
        sd = np.stack([gx, gy, gx * ox, gx * oy, gy * ox, gy * oy], axis=1)  # (n, 6, m)
        sdw = sd * g.w
        h = (sdw @ sd.transpose(0, 2, 1)).astype(np.float64) + 1e-6 * np.eye(6)
        return tm, np.maximum((tm * tm).sum(axis=1), 1e-6), sdw, np.linalg.inv(h).astype(np.float32)

    def _kept(self, rows: NDArray[np.bool_]) -> PatchTemplates:
        return PatchTemplates(self.grid, self.ids[rows], self.tm[rows], self.tss[rows], self.sdw[rows],
                              self.hinv[rows], self.A[rows])

    def _set(self, img: F32, pts: F64, ids: NDArray[np.int64]) -> PatchTemplates:
        """Templates for ``ids`` (unique) from ``img`` at ``pts``, replacing those already held; a point whose
        patch leaves the image loses its template."""
        ok = self._inside(img.shape, pts)
        pos = np.minimum(np.searchsorted(self.ids, ids), max(len(self) - 1, 0))
        held = self.ids[pos] == ids if len(self) else np.zeros(ids.shape[0], bool)
        out = self
        if ok.any():
            tm, tss, sdw, hinv = self._templates(img, pts[ok])
            at = pos[ok]
            replace = held[ok]
            k = at[replace]
            new_tm, new_tss, new_sdw, new_hinv = self.tm.copy(), self.tss.copy(), self.sdw.copy(), self.hinv.copy()
            new_A = self.A.copy()
            new_tm[k], new_tss[k] = tm[replace], tss[replace]
            new_sdw[k], new_hinv[k] = sdw[replace], hinv[replace]
            new_A[k] = np.eye(2)
            new_ids = self.ids
            add = ~replace
            if add.any():
                order = np.argsort(np.concatenate([new_ids, ids[ok][add]]), kind="stable")
                new_ids = np.concatenate([new_ids, ids[ok][add]])[order]
                new_tm = np.concatenate([new_tm, tm[add]])[order]
                new_tss = np.concatenate([new_tss, tss[add]])[order]
                new_sdw = np.concatenate([new_sdw, sdw[add]])[order]
                new_hinv = np.concatenate([new_hinv, hinv[add]])[order]
                new_A = np.concatenate([new_A, np.broadcast_to(np.eye(2), (int(add.sum()), 2, 2))])[order]
            out = PatchTemplates(self.grid, new_ids, new_tm, new_tss, new_sdw, new_hinv, new_A)
        if (held & ~ok).any():
            out = out._kept(~np.isin(out.ids, ids[held & ~ok]))
        return out

    def anchored(self, gray: NDArray[np.uint8], pts: F32, ids: NDArray[np.int64]) -> PatchTemplates:
        """At a keyframe: templates for the tracks new in it (from ``gray``), and only its tracks kept."""
        out = self._kept(np.isin(self.ids, ids))
        new = ~np.isin(ids, out.ids)
        if new.any():
            out = out._set(gray.astype(np.float32), pts[new].astype(np.float64), ids[new])
        return out

    def refined(self, gray: NDArray[np.uint8], pts: F32, ids: NDArray[np.int64]) -> tuple[PatchTemplates, F32, int]:
        """The templates after this frame, the tracked points ``pts`` (N, 2) of tracks ``ids`` moved to their
        templates' affine fit in ``gray``, and how many were moved. Tracks without a template, or whose fit
        fails, keep their position (a failed one's template is taken again from ``gray`` there)."""
        out = pts.astype(np.float64)
        if pts.shape[0] == 0 or len(self) == 0:
            return self, pts, 0
        img = gray.astype(np.float32)
        pos = np.minimum(np.searchsorted(self.ids, ids), len(self) - 1)
        have = self.ids[pos] == ids
        rows = np.flatnonzero(have)
        k = pos[rows]
        inside = self._inside(gray.shape, out[rows], self.A[k])
        rows, k = rows[inside], k[inside]
        if rows.size == 0:
            return self, pts, 0
        g = self.grid
        t, A = out[rows], self.A[k]  # fancy indexing copies
        tm, tss, sdw, hinv = self.tm[k], self.tss[k], self.sdw[k], self.hinv[k]
        ncc = np.zeros(rows.size, np.float32)
        for _ in range(REFINE_ITERATIONS):
            iw = _sample(img, t, A, g.ox, g.oy)
            e = iw - iw.mean(axis=1, keepdims=True)
            cross = (e * tm).sum(axis=1)
            # the fit's correlation with its template, before this step (the step only improves it)
            ncc = cross / np.sqrt(np.maximum((e * e).sum(axis=1), 1e-6) * tss)
            gain = np.maximum(cross / tss, 0.2)
            err = e / gain[:, None] - tm
            dp = (hinv @ (sdw @ err[:, :, None]))[:, :, 0].astype(np.float64)
            # inverse composition: W <- W o dW^-1, dW(x) = (I + dA) x + dt
            a, b, c, d = 1.0 + dp[:, 2], dp[:, 3], dp[:, 4], 1.0 + dp[:, 5]
            det = a * d - b * c
            det = np.where(np.abs(det) > 1e-6, det, 1e-6)
            inv = np.stack([np.stack([d, -b], 1), np.stack([-c, a], 1)], 1) / det[:, None, None]
            t = t - (A @ (inv @ dp[:, :2, None]))[:, :, 0]
            A = A @ inv
            if not np.max(np.abs(dp[:, :2])) >= REFINE_STOP_PX:  # also stops on NaN (then rejected below)
                break
        finite = np.isfinite(t).all(axis=1) & np.isfinite(A).all(axis=(1, 2)) & np.isfinite(ncc)
        t, A = np.where(finite[:, None], t, out[rows]), np.where(finite[:, None, None], A, self.A[k])
        sv_max, sv_min = _singular_values(A)
        scale = np.sqrt(sv_max * sv_min)
        good = (finite & (np.linalg.norm(t - out[rows], axis=1) <= REFINE_MAX_SHIFT_PX)
                & (ncc >= REFINE_MIN_NCC) & (sv_max <= REFINE_MAX_ANISOTROPY * sv_min)
                & self._inside(gray.shape, t, A))
        out[rows[good]] = t[good]
        warps = self.A.copy()
        warps[k[good]] = A[good]
        after = PatchTemplates(self.grid, self.ids, self.tm, self.tss, self.sdw, self.hinv, warps)
        again = ~good | (scale < REFINE_SCALE_RANGE[0]) | (scale > REFINE_SCALE_RANGE[1])
        if again.any():
            after = after._set(img, out[rows[again]], ids[rows[again]])
        return after, out.astype(np.float32), int(np.count_nonzero(good))


def patch_templates(cfg: VoConfig) -> PatchTemplates | None:
    """The refinement ``cfg`` asks for: None when ``klt_patch_refine_px`` is 0 or the frontend is not KLT."""
    refine = cfg.klt_patch_refine_px and cfg.frontend is Frontend.KLT
    return PatchTemplates.empty(cfg.klt_patch_refine_px) if refine else None
