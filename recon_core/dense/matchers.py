"""Stereo matchers behind one small interface: a rectified 8-bit pair and a disparity range in,
a disparity field and its validity out. `DenseConfig.matcher` picks one by name; its parameters
are the configuration section of the same name.

Convention: rows are epipolar lines; the disparity of a left pixel u is d = u_right - u_left
(the project's x2' - x1'), in pixels, NaN where invalid.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import cv2
import numpy as np

from recon_core.config import Config, SgbmConfig


class StereoMatcher(Protocol):
    """What dense matching needs of a matcher (picklable: jobs carry it to worker processes)."""

    @property
    def margin_px(self) -> int:
        """Context (px) the matcher needs beyond the disparity range at the canvas borders."""

    def match(self, left: np.ndarray, right: np.ndarray, d_lo: float, d_hi: float
              ) -> tuple[np.ndarray, np.ndarray]:
        """left, right: (h, w) uint8 rectified images; d_lo <= d <= d_hi the expected range.
        Returns d (h, w) float32 (NaN where invalid) and valid (h, w) bool."""


def sgbm_params(d_lo: float, d_hi: float) -> tuple[int, int]:
    """OpenCV (minDisparity, numDisparities) for d = x2' - x1' in [d_lo, d_hi].

    OpenCV matches left(x) with right(x - D), so D = -d; numDisparities is a multiple of 16.
    """
    min_d = int(np.floor(-d_hi))
    num = int(np.ceil((d_hi - d_lo + 1) / 16.0)) * 16
    return min_d, max(16, num)


def run_sgbm(left: np.ndarray, right: np.ndarray, min_d: int, num_d: int, cfg: SgbmConfig) -> np.ndarray:
    """StereoSGBM disparity D (float32, px; NaN invalid) with left(x) ~ right(x - D)."""
    bs = cfg.block_size
    sgbm = cv2.StereoSGBM_create(minDisparity=min_d, numDisparities=num_d, blockSize=bs,
                                 P1=cfg.p1 * bs * bs, P2=cfg.p2 * bs * bs, disp12MaxDiff=-1,
                                 uniquenessRatio=cfg.uniqueness, speckleWindowSize=cfg.speckle_window,
                                 speckleRange=cfg.speckle_range, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    raw = sgbm.compute(left, right)
    D = raw.astype(np.float32) / 16.0
    D[raw <= (min_d - 1) * 16] = np.nan
    return D


def lr_consistent(D_left: np.ndarray, D_right: np.ndarray, tol: float) -> np.ndarray:
    """Left-right check: D_right is the right image's disparity (right(x) ~ left(x + D_right))."""
    h, w = D_left.shape
    xs = np.arange(w)[None, :] - np.nan_to_num(D_left)
    xr = np.clip(np.round(xs).astype(np.int64), 0, w - 1)
    back = np.take_along_axis(D_right, xr, axis=1)
    ok = np.isfinite(D_left) & np.isfinite(back) & (np.abs(back - D_left) <= tol) & (xs >= 0) & (xs <= w - 1)
    return ok


@dataclass(frozen=True)
class SgbmMatcher:
    """OpenCV StereoSGBM, 3-way, with a true left-right check from a run on the mirrored pair."""

    cfg: SgbmConfig = field(default_factory=SgbmConfig)

    @property
    def margin_px(self) -> int:
        return self.cfg.block_size

    def match(self, left: np.ndarray, right: np.ndarray, d_lo: float, d_hi: float
              ) -> tuple[np.ndarray, np.ndarray]:
        min_d, num_d = sgbm_params(d_lo, d_hi)
        D = run_sgbm(left, right, min_d, num_d, self.cfg)
        Dr = run_sgbm(right[:, ::-1].copy(), left[:, ::-1].copy(), min_d, num_d, self.cfg)[:, ::-1]
        ok = lr_consistent(D, Dr, self.cfg.lr_max_diff_px)
        return np.where(ok, -D, np.nan).astype(np.float32), ok


MATCHERS = {"sgbm": SgbmMatcher}


def make_matcher(cfg: Config) -> StereoMatcher:
    """The matcher named by cfg.dense.matcher, with its configuration section."""
    name = cfg.dense.matcher
    if name not in MATCHERS:
        raise ValueError(f"unknown stereo matcher {name!r}; choose from {sorted(MATCHERS)}")
    return MATCHERS[name](getattr(cfg, name))
