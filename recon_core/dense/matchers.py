"""Stereo matchers behind one small interface: a rectified 8-bit pair and a disparity range in,
a disparity field and its validity out. `DenseConfig.matcher` picks one by name; its parameters
are the configuration section of the same name.

- `sgbm`: OpenCV's StereoSGBM.
- `mgm`: MGM on a census cost, the paper's matcher (and s2p's), built in (recon_core.dense.mgm).
- `pandora`: CNES's pandora with pandora_plugin_libsgm (census, SGM, V-fit, cross-checking), as
  CNES CARS configures it for satellite pairs; an optional extra (`pip install 'aerec[pandora]'`),
  imported only when used.

Convention: rows are epipolar lines; the disparity of a left pixel u is d = u_right - u_left
(the project's x2' - x1'), in pixels, NaN where invalid.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import cv2
import numpy as np

from recon_core.config import Config, MgmConfig, PandoraConfig, SgbmConfig


class StereoMatcher(Protocol):
    """What dense matching needs of a matcher (picklable: jobs carry it to worker processes)."""

    @property
    def margin_px(self) -> int:
        """Context (px) the matcher needs beyond the disparity range at the canvas borders."""
        ...

    def match(self, left: np.ndarray, right: np.ndarray, d_lo: float, d_hi: float
              ) -> tuple[np.ndarray, np.ndarray]:
        """left, right: (h, w) uint8 rectified images; d_lo <= d <= d_hi the expected range.
        Returns d (h, w) float32 (NaN where invalid) and valid (h, w) bool."""
        ...


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
    sgbm = cv2.StereoSGBM_create(minDisparity=min_d, numDisparities=num_d, blockSize=bs,  # pyright: ignore[reportAttributeAccessIssue]
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


@dataclass(frozen=True)
class MgmMatcher:
    """MGM (recon_core.dense.mgm): census cost, 8 directions of two-neighbour messages, WTA,
    V-fit, left-right check from the same aggregated costs, 3 x 3 median, speckle filter."""

    cfg: MgmConfig = field(default_factory=MgmConfig)

    @property
    def margin_px(self) -> int:
        return self.cfg.census_window // 2 + 2

    def match(self, left: np.ndarray, right: np.ndarray, d_lo: float, d_hi: float
              ) -> tuple[np.ndarray, np.ndarray]:
        from recon_core.dense.mgm import mgm_disparity

        c = self.cfg
        d = mgm_disparity(left, right, d_lo, d_hi, census_window=c.census_window, p1=c.p1, p2=c.p2,
                          lr_max_diff_px=c.lr_max_diff_px, median=c.median, speckle_window=c.speckle_window,
                          speckle_range=c.speckle_range, uniqueness=c.uniqueness, max_volume_mb=c.max_volume_mb)
        return d, np.isfinite(d)


# -- pandora (CNES) ------------------------------------------------------------------------------
def pandora_pipeline(cfg: PandoraConfig) -> dict:
    """Pandora's pipeline section for these parameters: CARS's census_sgm_default profile
    (census 5 x 5, SGM P1 = 8 / P2 = 32 constant, no overcounting, WTA, V-fit, 3 x 3 median) with
    the accurate cross-checking CARS adds (the right image's disparity computed too)."""
    pipe = {
        "matching_cost": {"matching_cost_method": "census", "window_size": cfg.census_window, "subpix": 1},
        "optimization": {"optimization_method": "sgm", "overcounting": False,
                         "penalty": {"penalty_method": "sgm_penalty", "P1": float(cfg.p1), "P2": float(cfg.p2),
                                     "p2_method": "constant"}},
        "disparity": {"disparity_method": "wta", "invalid_disparity": "NaN"},
        "refinement": {"refinement_method": cfg.refinement},
    }
    if cfg.median_size > 1:
        pipe["filter"] = {"filter_method": "median", "filter_size": cfg.median_size}
    pipe["validation"] = {"validation_method": "cross_checking_accurate",
                          "cross_checking_threshold": float(cfg.lr_max_diff_px)}
    return {"pipeline": pipe}


def _pandora_dataset(img: np.ndarray | None, shape: tuple[int, int], d_min: int, d_max: int):
    """The xarray.Dataset pandora reads for one image (img None: its metadata only, what pandora
    checks a configuration against): band-less, no nodata, one disparity range for every pixel."""
    import xarray as xr  # pyright: ignore[reportMissingImports]
    from pandora.img_tools import add_disparity  # pyright: ignore[reportMissingImports]

    h, w = shape
    coords = {"row": np.arange(h), "col": np.arange(w)}
    if img is None:
        ds = xr.Dataset(coords={"band_im": [None], **coords})
    else:
        ds = xr.Dataset({"im": (["row", "col"], img.astype(np.float32))}, coords=coords,
                        attrs={"crs": None, "transform": None, "valid_pixels": 0, "no_data_mask": 1,
                               "no_data_img": -9999})
    return add_disparity(ds, [d_min, d_max], None)


_PANDORA_READY = False


def _pandora_import():
    """pandora and its plugins, loaded once per process (its state machine's warnings hushed)."""
    global _PANDORA_READY
    import logging

    import pandora  # pyright: ignore[reportMissingImports]

    if not _PANDORA_READY:
        # pandora sets "transitions" to WARNING at each run; its core's binding notes are noise
        logging.getLogger("transitions.core").setLevel(logging.ERROR)
        pandora.import_plugin()
        _PANDORA_READY = True
    return pandora


@dataclass(frozen=True)
class PandoraMatcher:
    """CNES's pandora + pandora_plugin_libsgm: census cost, SGM (8 directions), WTA, sub-pixel
    refinement, median filter, accurate cross-checking. Pandora's disparity is col_right -
    col_left, the convention here. Holds only its parameters (picklable); pandora is imported in
    the process that matches."""

    cfg: PandoraConfig = field(default_factory=PandoraConfig)

    @property
    def margin_px(self) -> int:
        return self.cfg.census_window // 2 + self.cfg.median_size // 2 + 1

    def match(self, left: np.ndarray, right: np.ndarray, d_lo: float, d_hi: float
              ) -> tuple[np.ndarray, np.ndarray]:
        import copy

        pandora = _pandora_import()
        from pandora.check_configuration import check_pipeline_section  # pyright: ignore[reportMissingImports]
        from pandora.constants import Criteria  # pyright: ignore[reportMissingImports]
        from pandora.state_machine import PandoraMachine  # pyright: ignore[reportMissingImports]

        d_min, d_max = int(np.floor(d_lo)), int(np.ceil(d_hi))
        if d_max <= d_min:
            d_max = d_min + 1
        shape = left.shape
        machine = PandoraMachine()
        conf = check_pipeline_section(copy.deepcopy(pandora_pipeline(self.cfg)),
                                      _pandora_dataset(None, shape, d_min, d_max),
                                      _pandora_dataset(None, shape, -d_max, -d_min), machine)
        out_left, _ = pandora.run(machine, _pandora_dataset(left, shape, d_min, d_max),
                                  _pandora_dataset(right, shape, -d_max, -d_min), conf)
        d = np.asarray(out_left["disparity_map"].values, np.float32)
        flags = np.asarray(out_left["validity_mask"].values)
        ok = np.isfinite(d) & ((flags & int(Criteria.PANDORA_MSK_PIXEL_INVALID)) == 0)
        return np.where(ok, d, np.nan).astype(np.float32), ok


MATCHERS = {"sgbm": SgbmMatcher, "mgm": MgmMatcher, "pandora": PandoraMatcher}


def make_matcher(cfg: Config) -> StereoMatcher:
    """The matcher named by cfg.dense.matcher, with its configuration section."""
    name = cfg.dense.matcher
    if name not in MATCHERS:
        raise ValueError(f"unknown stereo matcher {name!r}; choose from {sorted(MATCHERS)}")
    return MATCHERS[name](getattr(cfg, name))
