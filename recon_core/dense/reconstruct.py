"""Dense affine reconstruction: rectification, semi-global matching, dense tracks, triangulation.

Work is organised per *reference tile* (never a union-find over millions of pixels of the whole
group): for a registered tile r
of image a, every overlapping registered tile t of a later image b is a partner. For each pair:
  1. F_A from the two tile cameras (the Gold Standard estimate from the sparse matches is the
     check), two rectifying affine maps (s2p's construction, `affine.rectifying_maps`);
  2. the disparity range from the sparse matches' rectified disparities (percentiles + margin);
  3. OpenCV StereoSGBM on the 8-bit rectified pair (one tone curve for both), a second run on the
     mirrored pair for a true left-right check, speckle removal.
Each reference pixel then has at most one correspondence per partner image; links whose 5 x 5
patches disagree photometrically (NCC after warping by the local affine map between the views)
are dropped; each track is triangulated with all its views (linear multi-view affine
triangulation = minimal reprojection error for fixed cameras); views with a large error are
dropped and the point re-triangulated (the only useful "refinement" for fixed affine cameras).

Jobs (`DenseJob`) hold paths, windows and cameras, never image arrays: workers read windows.
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from recon_core.config import DenseConfig
from recon_core.dense.matchers import SgbmMatcher, StereoMatcher
from recon_core.errors import ReconstructionError
from recon_core.geometry import affine
from recon_core.geometry.camera import AffineCamera
from recon_core.io.models import dense_writer
from recon_core.io.site import ImageInfo, read_window
from recon_core.model.dense_cloud import DenseCloud
from recon_core.model.sparse_model import CorrectionField
from recon_core.model.tiling import Tile


@dataclass
class TileSpec:
    image: ImageInfo
    tile: Tile
    camera: np.ndarray                 # (2, 4) full-image pixels
    correction: CorrectionField | None = None   # the SfM's within-tile correction: the camera
    #                                             sees a pixel minus it


@dataclass
class PartnerSpec:
    spec: TileSpec
    x_ref: np.ndarray                  # (n, 2) sparse matches in the reference image (full pixels)
    x_partner: np.ndarray              # (n, 2) the same in the partner image
    core: tuple[int, int, int, int] | None = None   # the partner tile's own part (full image)


@dataclass
class DenseJob:
    group: int
    ref: TileSpec
    core: tuple[int, int, int, int]    # (c0, r0, c1, r1) full-image window whose pixels this job owns
    partners: list[PartnerSpec]
    cfg: DenseConfig
    matcher: StereoMatcher = field(default_factory=SgbmMatcher)
    sigma_best: float | None = None    # the group's best image pair's triangulation spread
                                       # (pair_spread); None = no two-view precision test


@dataclass
class PairInfo:
    ref: str
    partner: str
    n_sparse: int
    parallax: float
    fa_cam_rms_px: float               # RMS 4D residual of the sparse matches under F from the cameras
    fa_gs_rms_px: float                # ... under the Gold Standard F_A fitted to them (the check)
    row_err_px: float                  # median |y1' - y2'| of sparse matches after rectification
    disp_range: tuple[float, float]
    valid_frac: float                  # reference pixels with an LR-consistent disparity
    kernel_s: float
    skipped: str | None = None


@dataclass
class DenseResult:
    group: int
    ref: str
    xyz: np.ndarray                    # (n, 3) affine frame
    gray: np.ndarray                   # (n,) uint8
    n_views: np.ndarray                # (n,) uint8
    reproj_px: np.ndarray              # (n,) float32 RMS over the views
    pairs: list[PairInfo] = field(default_factory=list)
    seconds: float = 0.0
    kernel_s: float = 0.0
    message: str | None = None
    weak: np.ndarray | None = None     # (n,) bool: a two-view point of a weak pair (DSM fallback)


# -- pair geometry ----------------------------------------------------------------------------

def local_camera(P: np.ndarray, tile: Tile) -> np.ndarray:
    """Camera (2, 4) in tile-local pixels (tile pixel (0, 0) = full pixel (col0, row0))."""
    return AffineCamera.from_array(P).in_window(tile.col0, tile.row0).to_array()


def disparity_range(d: np.ndarray, margin_px: float, margin_frac: float) -> tuple[float, float]:
    """Robust range of the sparse disparities (2nd-98th percentiles) widened by margins."""
    lo, hi = np.percentile(d, [2.0, 98.0])
    m = margin_px + margin_frac * (hi - lo)
    return float(lo - m), float(hi + m)


def to_8bit_pair(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One tone curve for both images: joint 0.5-99.5 percentiles, then a square root. Images
    of different kinds (radiometric ranges that barely overlap: a float reflectance image
    beside 12-bit counts: robust widths 20x apart or more) get a curve each, or the joint one
    would crush one of them to black; a dark and a bright image of one kind keep the joint one."""
    va, vb = (x[np.isfinite(x)].ravel()[::7] for x in (a, b))
    v = np.concatenate([va, vb])
    lo, hi = np.percentile(v, [0.5, 99.5]) if len(v) else (0.0, 1.0)

    def conv(x, lo, hi):
        t = np.clip((x - lo) / max(hi - lo, 1e-6), 0, 1)
        return (np.sqrt(np.nan_to_num(t)) * 255 + 0.5).astype(np.uint8)

    if len(va) and len(vb):
        (la, ha), (lb, hb) = np.percentile(va, [0.5, 99.5]), np.percentile(vb, [0.5, 99.5])
        wa, wb = max(ha - la, 1e-12), max(hb - lb, 1e-12)
        if max(wa, wb) > 20.0 * min(wa, wb):
            return conv(a, la, ha), conv(b, lb, hb)
    return conv(a, lo, hi), conv(b, lo, hi)


def match_pair(ref_img: np.ndarray, ref: TileSpec, part_img: np.ndarray, p: PartnerSpec,
               cfg: DenseConfig, ref_core: tuple[int, int, int, int] | None = None,
               matcher: StereoMatcher | None = None) -> tuple[dict | None, PairInfo]:
    """Rectify and match one tile pair; returns the rectified disparity field and its maps.

    ref_core / p.core: the full-image boxes each tile owns (None = the whole tile).
    matcher: the stereo matcher (default: SGBM with its default parameters, the fastest; the
    dense stage passes the configured one, make_matcher).
    """
    matcher = matcher or SgbmMatcher()
    rt, pt = ref.tile, p.spec.tile
    P1, P2 = local_camera(ref.camera, rt), local_camera(p.spec.camera, pt)
    x1 = p.x_ref - (rt.col0, rt.row0)
    x2 = p.x_partner - (pt.col0, pt.row0)
    par = affine.parallax_ratio(x1, x2) if len(x1) >= 5 else 0.0
    info = PairInfo(rt.id, pt.id, len(x1), float(par), float("nan"), float("nan"), float("nan"),
                    (0.0, 0.0), 0.0, 0.0)
    if len(x1) < cfg.min_pair_matches:
        info.skipped = f"{len(x1)} sparse matches < {cfg.min_pair_matches}"
        return None, info
    try:
        F = affine.affine_fundamental_from_cameras(P1, P2)
        H1, H2 = affine.rectifying_maps(F, x1, x2)
    except ReconstructionError as exc:
        info.skipped = str(exc)
        return None, info
    F_gs = affine.affine_fundamental_gold_standard(x1, x2)
    info.fa_cam_rms_px = float(np.sqrt(np.mean(affine.fa_residuals(F, x1, x2) ** 2)))
    info.fa_gs_rms_px = float(np.sqrt(np.mean(affine.fa_residuals(F_gs, x1, x2) ** 2)))
    info.row_err_px = float(np.median(np.abs(affine.rectified_row_error(H1, H2, x1, x2))))
    d_sparse = affine.apply_affine_2d(H2, x2)[:, 0] - affine.apply_affine_2d(H1, x1)[:, 0]
    d_lo, d_hi = disparity_range(d_sparse, cfg.disp_margin_px, cfg.disp_margin_frac)
    info.disp_range = (d_lo, d_hi)

    # Canvas: the rectified box of the reference pixels this job owns (the core), rows limited
    # to those the partner's own part covers, padded horizontally so the whole disparity range
    # stays inside the partner's canvas. Tiles of one image overlap (d/3): matching only the
    # cores (plus a context margin for the aggregation paths) avoids matching every pixel pair
    # about 2.25 x 2.25 times; the neighbouring tile pairs cover the rest.
    c1 = affine.apply_affine_2d(H1, _box_corners(ref_core, rt, cfg.core_margin_px))
    c2 = affine.apply_affine_2d(H2, _box_corners(p.core, pt, cfg.core_margin_px))
    v0, v1 = max(c1[:, 1].min(), c2[:, 1].min()), min(c1[:, 1].max(), c2[:, 1].max())
    if v1 - v0 < 16:
        info.skipped = NOT_NEEDED if p.core or ref_core else "rectified tiles share fewer than 16 rows"
        return None, info
    pad = int(np.ceil(max(abs(d_lo), abs(d_hi)))) + matcher.margin_px + 2
    # columns of the reference whose match can fall on the partner: u = x2' - d
    ua = max(c1[:, 0].min(), c2[:, 0].min() - d_hi)
    ub = min(c1[:, 0].max(), c2[:, 0].max() - d_lo)
    if ub - ua < 16:
        info.skipped = NOT_NEEDED if p.core or ref_core else "rectified tiles share fewer than 16 columns"
        return None, info
    u0 = int(np.floor(ua)) - pad
    v0 = int(np.floor(v0))
    W = int(np.ceil(ub)) + pad - u0
    Hh = int(np.ceil(v1)) - v0
    T = np.array([[1.0, 0, -u0], [0, 1.0, -v0], [0, 0, 1.0]])
    A1, A2 = T @ H1, T @ H2
    l8, r8 = to_8bit_pair(ref_img, part_img)
    left = cv2.warpAffine(l8, A1[:2], (W, Hh), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    right = cv2.warpAffine(r8, A2[:2], (W, Hh), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    m1 = cv2.warpAffine(np.isfinite(ref_img).astype(np.uint8), A1[:2], (W, Hh), flags=cv2.INTER_NEAREST) > 0
    m2 = cv2.warpAffine(np.isfinite(part_img).astype(np.uint8), A2[:2], (W, Hh), flags=cv2.INTER_NEAREST) > 0
    t0 = time.perf_counter()
    d, valid = matcher.match(left, right, d_lo, d_hi)           # d = x2' - x1'
    info.kernel_s = time.perf_counter() - t0
    ok = valid & m1
    # the matched right pixel must lie on the partner tile
    xs = np.clip(np.round(np.arange(W)[None, :] + np.nan_to_num(d)).astype(np.int64), 0, W - 1)
    ok &= np.take_along_axis(m2, xs, axis=1)
    d = np.where(ok, d, np.nan).astype(np.float32)
    return {"A1": A1, "A2": A2, "d": d, "J": np.linalg.inv(H2[:2, :2]) @ H1[:2, :2]}, info


NOT_NEEDED = "the parts the two tiles own do not overlap (neighbouring tile pairs cover it)"


def _corners(t: Tile) -> np.ndarray:
    return np.array([[-0.5, -0.5], [t.width - 0.5, -0.5], [t.width - 0.5, t.height - 0.5],
                     [-0.5, t.height - 0.5]])


def _box_corners(core: tuple[int, int, int, int] | None, t: Tile, margin: int) -> np.ndarray:
    """Tile-local corners of a full-image box (c0, r0, c1, r1) grown by margin, clipped to the tile."""
    if core is None:
        return _corners(t)
    c0, r0, c1, r1 = core
    a0 = max(c0 - margin - t.col0, 0) - 0.5
    b0 = max(r0 - margin - t.row0, 0) - 0.5
    a1 = min(c1 + margin - t.col0, t.width) - 0.5
    b1 = min(r1 + margin - t.row0, t.height) - 0.5
    return np.array([[a0, b0], [a1, b0], [a1, b1], [a0, b1]])


def sample_disparity(d: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Disparity at canvas positions (n, 2): bilinear where the 4 neighbours agree within 1 px,
    nearest otherwise (no blending across depth edges); NaN outside or invalid."""
    h, w = d.shape
    u, v = uv[:, 0], uv[:, 1]
    inside = (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    out = np.full(len(uv), np.nan, np.float32)
    u, v = u[inside], v[inside]
    x0 = np.clip(np.floor(u).astype(np.int64), 0, w - 2)
    y0 = np.clip(np.floor(v).astype(np.int64), 0, h - 2)
    fx, fy = (u - x0).astype(np.float32), (v - y0).astype(np.float32)
    q = np.stack([d[y0, x0], d[y0, x0 + 1], d[y0 + 1, x0], d[y0 + 1, x0 + 1]], 1)
    bil = (q[:, 0] * (1 - fx) * (1 - fy) + q[:, 1] * fx * (1 - fy) + q[:, 2] * (1 - fx) * fy
           + q[:, 3] * fx * fy)
    spread = q.max(axis=1) - q.min(axis=1)          # NaN where a neighbour is invalid
    near = d[np.clip(np.round(v).astype(np.int64), 0, h - 1), np.clip(np.round(u).astype(np.int64), 0, w - 1)]
    val = np.where(np.all(np.isfinite(q), axis=1) & (spread <= 1.0), bil, near)
    out[np.flatnonzero(inside)] = val
    return out


def patch_ncc(ref_img: np.ndarray, p: np.ndarray, part_img: np.ndarray, q: np.ndarray, J: np.ndarray,
              radius: int) -> np.ndarray:
    """NCC (n,) of (2r+1)^2 patches: around integer pixels p (tile-local) in the reference and
    around q in the partner, the partner patch warped by the local affine map J (2 x 2)."""
    o = np.arange(-radius, radius + 1, dtype=np.float32)
    oy, ox = np.meshgrid(o, o, indexing="ij")
    off = np.stack([ox.ravel(), oy.ravel()], 1)                   # (k, 2)
    woff = off @ J.T.astype(np.float32)
    out = np.empty(len(p), np.float32)
    ref = np.nan_to_num(ref_img).astype(np.float32)
    part = np.nan_to_num(part_img).astype(np.float32)
    step = 30_000                          # cv2.remap maps must stay below 32767 rows
    for s in range(0, len(p), step):
        pp, qq = p[s:s + step], q[s:s + step]
        a = ref[np.clip(pp[:, 1:2] + off[None, :, 1].astype(np.int64), 0, ref.shape[0] - 1),
                np.clip(pp[:, 0:1] + off[None, :, 0].astype(np.int64), 0, ref.shape[1] - 1)]
        mx = (qq[:, 0:1] + woff[None, :, 0]).astype(np.float32)
        my = (qq[:, 1:2] + woff[None, :, 1]).astype(np.float32)
        b = cv2.remap(part, mx, my, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        a = a - a.mean(1, keepdims=True)
        b = b - b.mean(1, keepdims=True)
        den = np.sqrt((a * a).sum(1) * (b * b).sum(1))
        out[s:s + step] = np.where(den > 1e-6, (a * b).sum(1) / np.maximum(den, 1e-12), 0.0)
    return out


# -- the job ----------------------------------------------------------------------------------

def run_job(job: DenseJob) -> DenseResult:
    """Dense points owned by one reference tile, from all its partner tile pairs."""
    t_start = time.time()
    cfg, ref = job.cfg, job.ref
    rt = ref.tile
    ref_img = read_window(ref.image, rt.col0, rt.row0, rt.width, rt.height)
    c0, r0, c1, r1 = job.core
    gy, gx = np.mgrid[r0:r1:cfg.step, c0:c1:cfg.step]
    pix = np.stack([gx.ravel(), gy.ravel()], 1).astype(np.int64)     # full-image reference pixels
    loc = pix - (rt.col0, rt.row0)
    n = len(pix)
    # best link per partner image: (q full-image, camera index, centrality)
    images = sorted({p.spec.image.name for p in job.partners})
    cams = [ref.camera]
    fields = [ref.correction]
    best_q = {im: np.full((n, 2), np.nan) for im in images}
    best_cam = {im: np.full(n, -1, np.int64) for im in images}
    best_c = {im: np.full(n, np.inf) for im in images}
    infos, kernel = [], 0.0
    for p in job.partners:
        pt = p.spec.tile
        part_img = read_window(p.spec.image, pt.col0, pt.row0, pt.width, pt.height)
        res, info = match_pair(ref_img, ref, part_img, p, cfg, job.core, job.matcher)
        infos.append(info)
        kernel += info.kernel_s
        if res is None:
            continue
        uv = affine.apply_affine_2d(res["A1"], loc.astype(np.float64))
        hh, ww = res["d"].shape
        idx = np.flatnonzero((uv[:, 0] >= 0) & (uv[:, 0] <= ww - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= hh - 1))
        d = sample_disparity(res["d"], uv[idx])
        ok = np.isfinite(d)
        info.valid_frac = float(ok.sum() / max(len(idx), 1))
        idx, d = idx[ok], d[ok]
        q_rect = uv[idx] + np.stack([d, np.zeros(len(idx))], 1)
        q = affine.apply_affine_2d(np.linalg.inv(res["A2"]), q_rect)         # partner tile-local
        inside = (q[:, 0] >= 0) & (q[:, 0] <= pt.width - 1) & (q[:, 1] >= 0) & (q[:, 1] <= pt.height - 1)
        idx, q = idx[inside], q[inside]
        ncc = patch_ncc(ref_img, loc[idx], part_img, q, res["J"], cfg.ncc_radius)
        keep = ncc >= cfg.min_ncc
        idx, q = idx[keep], q[keep]
        centr = np.max(np.abs(q - (pt.width / 2.0, pt.height / 2.0)) / (pt.width / 2.0, pt.height / 2.0), axis=1)
        im = p.spec.image.name
        better = centr < best_c[im][idx]
        idx, q, centr = idx[better], q[better], centr[better]
        cams.append(p.spec.camera)
        fields.append(p.spec.correction)
        best_q[im][idx] = q + (pt.col0, pt.row0)
        best_cam[im][idx] = len(cams) - 1
        best_c[im][idx] = centr
    xyz, nv, err, keep_idx, pair = _triangulate(pix, cams, best_q, best_cam, cfg.max_reproj_px,
                                                cfg.view_drop_rounds, fields)
    weak = np.zeros(len(xyz), bool)
    if job.sigma_best and cfg.max_two_view_spread > 0 and len(xyz):
        # a two-view point's height is as precise as its pair's geometry: those of a pair far
        # weaker than the group's best (a small-angle pair) are marked, and the DSM uses them
        # only in cells no other point reaches
        spread = np.array([[pair_spread(a, b) for b in cams] for a in cams])
        weak = (nv == 2) & (spread[pair[:, 0], pair[:, 1]] > cfg.max_two_view_spread * job.sigma_best)
    g8, _ = to_8bit_pair(ref_img, ref_img)
    gray = g8[loc[keep_idx, 1], loc[keep_idx, 0]]
    needed = [i for i in infos if i.skipped != NOT_NEEDED]
    # a tile whose owned part overlaps no partner's owned part is covered by its neighbours' jobs
    msg = None if len(xyz) or not needed else \
        f"{rt.id}: no dense points ({'; '.join(i.skipped or 'no valid disparity' for i in needed)})"
    return DenseResult(job.group, rt.id, xyz, gray, nv.astype(np.uint8), err.astype(np.float32), infos,
                       time.time() - t_start, kernel, msg, weak)


def pair_spread(P1: np.ndarray, P2: np.ndarray) -> float:
    """How far a point triangulated by two affine cameras (2, 4) moves per pixel of image
    error, along its worst-determined direction (affine.views_spread of the pair). In one
    affine frame, pairs compare by it (a small intersection angle gives a large spread, mostly
    in height)."""
    return affine.views_spread([P1, P2])


def _triangulate(pix, cams, best_q, best_cam, max_err, rounds=3, fields=None):
    """Multi-view triangulation of reference pixels with their links; `fields`: each camera's
    within-tile correction (CorrectionField or None), subtracted from its pixels first.

    A point whose worst view is off by more than max_err loses that view (if it keeps >= 2)
    and is re-triangulated (`rounds` triangulations at most); points still off are dropped.
    Returns (X, views, RMS error, kept pixel indices, (k, 2) the lowest and highest camera index
    among each kept point's views: its pair when it has two).
    """
    n = len(pix)
    cams = np.array(cams)
    obs_pt, obs_cam, obs_xy = [np.arange(n)], [np.zeros(n, np.int64)], [pix.astype(np.float64)]
    for im in best_q:
        sel = np.flatnonzero(best_cam[im] >= 0)
        obs_pt.append(sel)
        obs_cam.append(best_cam[im][sel])
        obs_xy.append(best_q[im][sel])
    pt, cam, xy = np.concatenate(obs_pt), np.concatenate(obs_cam), np.concatenate(obs_xy)
    for c, f in enumerate(fields or []):
        if f is not None:
            k = np.flatnonzero(cam == c)
            xy[k] -= f(xy[k])
    use = np.ones(len(pt), bool)
    for it in range(rounds):
        X, ok = affine.triangulate_tracks(cams, cam[use], pt[use], xy[use], n)
        good = use & ok[pt]
        err = np.zeros(len(pt))
        err[good] = affine.reprojection_errors(cams, cam[good], pt[good], xy[good], X)
        nv = np.bincount(pt[good], minlength=n)
        worst = np.zeros(n)
        np.maximum.at(worst, pt[good], err[good])
        fixable = ok & (worst > max_err) & (nv >= 3)
        if it == rounds - 1 or not fixable.any():
            break
        use &= ~(good & fixable[pt] & (err >= worst[pt]))
    sq = np.bincount(pt[good], err[good] ** 2, minlength=n)
    keep = ok & (nv >= 2) & (worst <= max_err)
    rms = np.sqrt(sq / np.maximum(nv, 1))
    idx = np.flatnonzero(keep)
    lo = np.full(n, len(cams), np.int64)
    hi = np.full(n, -1, np.int64)
    np.minimum.at(lo, pt[good], cam[good])
    np.maximum.at(hi, pt[good], cam[good])
    return X[idx], nv[idx], rms[idx], idx, np.stack([lo[idx], hi[idx]], 1)


# -- planning and running a group --------------------------------------------------------------

def tile_core(tile: Tile, same_image: list[Tile]) -> tuple[int, int, int, int]:
    """The part of a tile it owns: overlaps with neighbouring tiles of its image split midway."""
    c0, r0 = tile.col0, tile.row0
    c1, r1 = tile.col0 + tile.width, tile.row0 + tile.height
    for t in same_image:
        if t.ti == tile.ti and t.tj == tile.tj - 1:
            c0 = (tile.col0 + t.col0 + t.width + 1) // 2
        if t.ti == tile.ti and t.tj == tile.tj + 1:
            c1 = (t.col0 + tile.col0 + tile.width + 1) // 2
        if t.tj == tile.tj and t.ti == tile.ti - 1:
            r0 = (tile.row0 + t.row0 + t.height + 1) // 2
        if t.tj == tile.tj and t.ti == tile.ti + 1:
            r1 = (t.row0 + tile.row0 + tile.height + 1) // 2
    return c0, r0, c1, r1


def plan_jobs(model, images: dict[str, ImageInfo], cfg: DenseConfig,
              matcher: StereoMatcher | None = None) -> list[DenseJob]:
    """One job per registered reference tile; partners are overlapping registered tiles of the
    images after it in the group's order (each tile pair is matched once)."""
    o = model.obs
    act = model.active_obs()
    tile_of, track_of, xy_of = o.tile[act], o.track[act], o.xy[act]
    order = {name: k for k, name in enumerate(model.images)}
    jobs = []
    reg = np.flatnonzero(model.registered)
    by_tile = {t: (track_of[tile_of == t], xy_of[tile_of == t]) for t in reg}
    fields = model.correction_fields(reg)
    # Baseline test per IMAGE pair (a near-zero-baseline pair is dropped): the best
    # sigma3/sigma4 over its tile pairs. A flat tile pair of a good image pair is still matched:
    # its low ratio says "no relief", not "no baseline".
    best_par: dict[tuple[str, str], float] = {}
    spreads: dict[tuple[str, str], list[float]] = {}
    for r in reg:
        for t in reg:
            a, b = model.tiles[r].image, model.tiles[t].image
            if order[a] >= order[b]:
                continue
            common, ia, ib = np.intersect1d(by_tile[r][0], by_tile[t][0], return_indices=True)
            if len(common) >= max(cfg.min_pair_matches, 30):
                par = affine.parallax_ratio(by_tile[r][1][ia], by_tile[t][1][ib])
                best_par[(a, b)] = max(best_par.get((a, b), 0.0), par)
                spreads.setdefault((a, b), []).append(pair_spread(model.cams[r], model.cams[t]))

    def _image_pair_has_parallax(a: str, b: str) -> bool:
        return best_par.get((a, b), 0.0) >= cfg.min_parallax_ratio
    # the two-view precision test's yardstick: the group's most precise image pair (the median
    # spread over its tile pairs)
    good = [float(np.median(v)) for k, v in spreads.items() if _image_pair_has_parallax(*k)]
    sigma_best = min(good) if good else None

    same_of: dict[str, list[Tile]] = {}
    for t in model.tiles:
        same_of.setdefault(t.image, []).append(t)
    for r in reg:
        rt = model.tiles[r]
        tr_r, xy_r = by_tile[r]
        partners = []
        for t in reg:
            tt = model.tiles[t]
            if order[tt.image] <= order[rt.image]:
                continue
            tr_t, xy_t = by_tile[t]
            common, ia, ib = np.intersect1d(tr_r, tr_t, return_indices=True)
            if len(common) < cfg.min_pair_matches:
                continue
            partners.append(PartnerSpec(TileSpec(images[tt.image], tt, model.cams[t].copy(),
                                                 fields[t]),
                                        xy_r[ia], xy_t[ib], tile_core(tt, same_of[tt.image])))
        if not partners:
            continue
        partners = [p for p in partners if _image_pair_has_parallax(rt.image, p.spec.image.name)]
        if not partners:
            continue
        jobs.append(DenseJob(model.group, TileSpec(images[rt.image], rt, model.cams[r].copy(),
                                                   fields[r]),
                             tile_core(rt, same_of[rt.image]), partners, cfg, matcher or SgbmMatcher(),
                             sigma_best))
    return jobs


def reconstruct_dense_group(model, images: dict[str, ImageInfo], cfg: DenseConfig, bus=None,
                            executor=None, path: Path | None = None,
                            matcher: StereoMatcher | None = None) -> tuple[DenseCloud | None, dict]:
    """Run every reference-tile job of a group through the executor and gather the cloud.

    With `path` the cloud is streamed to that PLY (recon_core.io.models' dense.ply format) and not held in
    memory: each job's points go to a scratch file as they arrive, then are copied in a fixed
    order (by reference tile, whatever the executor's completion order) into the PLY. Returns
    (None, summary) then; without `path`, (the cloud in memory, summary).
    """
    from recon_core.dense.executor import make_executor
    from recon_core.events import EventBus, PointsAdded

    bus = bus or EventBus()
    t0 = time.time()
    jobs = plan_jobs(model, images, cfg, matcher)
    own = executor is None
    ex = executor or make_executor(cfg.scheduler, cfg.workers,
                                   on_wait=lambda text: bus.message(text, "warning", model.group))
    tally = _DenseTally(cfg.max_reproj_px)
    if path is not None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=".dense_parts_", dir=None if path is None else Path(path).parent) as scratch:
        parts: dict[str, Path] = {}
        try:
            for k, res in enumerate(ex.map_unordered(run_job, jobs)):
                if res.message:
                    bus.message(res.message, "warning", model.group)
                ids, rec = tally.add(res)
                if rec is not None:
                    parts[res.ref] = Path(scratch) / f"{len(parts):06d}.npy"
                    np.save(parts[res.ref], rec)
                    bus.emit(PointsAdded(model.group, ids, res.xyz, np.repeat(res.gray[:, None], 3, 1),
                                         res.n_views.astype(np.int64), res.reproj_px, kind="dense"))
                del res
                bus.progress("dense", k + 1, len(jobs), f"{tally.next_id} points", group=model.group)
        finally:
            if own:
                ex.close()
        cloud = _gather_parts(parts, path, model.group)
    summary = tally.summary(jobs, time.time() - t0)
    if path is not None:
        summary["path"] = str(path)
    if not summary["points"]:
        bus.message(f"group {model.group}: dense matching produced no point", "warning", model.group)
    return cloud, summary


class _DenseTally:
    """What the jobs of a group returned, summed as they arrive: their tile pairs, times, points
    (by number of views), weak-pair points and reprojection errors (a histogram)."""

    def __init__(self, max_reproj_px: float):
        self.pairs, self.kernel, self.job_s, self.next_id, self.n_weak = [], 0.0, 0.0, 0, 0
        self.views_hist = np.zeros(256, np.int64)
        self.err_edges = np.linspace(0.0, max(max_reproj_px, 1e-3) * 1.001, 2001)
        self.err_hist = np.zeros(len(self.err_edges) - 1, np.int64)

    def add(self, res) -> tuple[np.ndarray, np.ndarray | None]:
        """File one job's result; returns (its points' ids, its points as a record, or None)."""
        self.pairs += res.pairs
        self.kernel += res.kernel_s
        self.job_s += res.seconds
        ids = np.arange(self.next_id, self.next_id + len(res.xyz))
        self.next_id += len(res.xyz)
        if not len(res.xyz):
            return ids, None
        self.views_hist += np.bincount(res.n_views, minlength=256)
        self.err_hist += np.histogram(np.minimum(res.reproj_px, self.err_edges[-1] * 0.999), self.err_edges)[0]
        rec = np.empty(len(res.xyz), _PART_DTYPE)
        rec["xyz"], rec["gray"], rec["n_views"], rec["reproj_px"] = res.xyz, res.gray, res.n_views, res.reproj_px
        rec["weak"] = False if res.weak is None else res.weak
        self.n_weak += int(rec["weak"].sum())
        return ids, rec

    def summary(self, jobs: list, wall: float) -> dict:
        n_points = int(self.views_hist.sum())
        pairs = self.pairs
        matched = [p for p in pairs if p.skipped is None]
        med_err = None
        if n_points:
            k = int(np.searchsorted(np.cumsum(self.err_hist), (n_points + 1) / 2))
            med_err = float(0.5 * (self.err_edges[k] + self.err_edges[k + 1]))
        kernel, job_s = self.kernel, self.job_s
        return {"jobs": len(jobs), "tile_pairs": sum(len(j.partners) for j in jobs), "pairs_matched": len(matched),
                "pairs_not_needed": sum(p.skipped == NOT_NEEDED for p in pairs),
                "pairs_skipped": {f"{p.ref}~{p.partner}": p.skipped for p in pairs
                                  if p.skipped and p.skipped != NOT_NEEDED},
                "points": n_points,
                "views_histogram": np.trim_zeros(self.views_hist, "b").tolist(),
                "weak_pair_points": self.n_weak,
                "median_reproj_px": med_err,
                "median_rectified_row_err_px": float(np.median([p.row_err_px for p in matched])) if matched else None,
                "median_fa_cam_rms_px": float(np.median([p.fa_cam_rms_px for p in matched])) if matched else None,
                "median_fa_gs_rms_px": float(np.median([p.fa_gs_rms_px for p in matched])) if matched else None,
                "matcher_kernel_s": kernel, "job_s": job_s, "wall_s": wall,
                "overhead_ratio_cpu": job_s / kernel if kernel > 0 else None}


def _gather_parts(parts: dict[str, Path], path: Path | None, group: int) -> DenseCloud | None:
    """The jobs' points in a fixed order (by reference tile): streamed into the PLY at `path`
    (None returned), or as one cloud in memory."""
    order = sorted(parts)            # deterministic order whatever the executor
    if path is not None:
        with dense_writer(path, group) as w:
            for ref in order:
                rec = np.load(parts[ref])
                w.append(rec["xyz"], rec["gray"][:, None], {"n_views": rec["n_views"].astype(np.float32),
                                                           "reproj_px": rec["reproj_px"],
                                                           "weak": rec["weak"].astype(np.float32)})
        return None
    recs = [np.load(parts[ref]) for ref in order]
    rec = np.concatenate(recs) if recs else np.zeros(0, _PART_DTYPE)
    return DenseCloud(rec["xyz"].copy(), rec["gray"].copy(), rec["n_views"].copy(),
                      rec["reproj_px"].copy(), rec["weak"].astype(bool))


_PART_DTYPE = np.dtype([("xyz", "<f8", 3), ("gray", "u1"), ("n_views", "u1"), ("reproj_px", "<f4"),
                        ("weak", "u1")])

