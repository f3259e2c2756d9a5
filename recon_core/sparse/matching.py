"""Which images overlap, guided SIFT matching per image pair, verification per tile pair.

1. A coarse match of downsampled whole images gives a 2D affine map between each pair of images
   (no RPC needed): it says which tiles overlap and guides the fine matching.
2. Fine matching per image pair: for each tile of image i, its features are matched (ratio
   test, mutual check) against the features of image j predicted to fall near that tile.
3. Verification per overlapping tile pair by an affine fundamental matrix in RANSAC (a pushbroom
   camera is nearly affine on a tile, not over a whole image).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from recon_core.config import MatchingConfig
from recon_core.geometry import affine
from recon_core.model.tiling import Tile
from recon_core.sparse.features import ImageFeatures


@dataclass
class CoarseLink:
    """2D affine map from image j's pixels to image i's pixels, from an overview match."""

    i: str
    j: str
    A_ji: np.ndarray          # (2, 3)
    n_inliers: int
    residual_px: float        # RMS of the overview fit in full-resolution pixels


@dataclass
class TilePairStats:
    tile_i: str
    tile_j: str
    n_matches: int            # candidate matches inside both tiles
    n_inliers: int            # F_A-verified
    parallax: float           # sigma3 / sigma4 of the centred 4 x n measurement matrix
    fa_rms_px: float


@dataclass
class PairMatches:
    """Verified matches between two images: feature indices into each image's features."""

    i: str
    j: str
    idx_i: np.ndarray         # (n,) int
    idx_j: np.ndarray         # (n,) int
    tile_pairs: list[TilePairStats] = field(default_factory=list)

    @property
    def n(self) -> int:
        return len(self.idx_i)


def _two_nearest(D: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Along `axis` of a squared-distance matrix with >= 2 entries on it: (index of the nearest,
    its squared distance, the second nearest's). D is restored before returning."""
    best = D.argmin(axis=axis)
    other = np.arange(len(best))
    at = (other, best) if axis == 1 else (best, other)
    d0 = D[at]
    D[at] = np.inf
    d1 = D.min(axis=axis)
    D[at] = d0
    return best, d0, d1


def match_descriptors(d1: np.ndarray, d2: np.ndarray, ratio: float, mutual: bool) -> tuple[np.ndarray, np.ndarray]:
    """Ratio-test (and optionally mutual) nearest neighbours: (idx1, idx2). Exact L2 distances
    from one matrix product (BLAS) that serves both directions."""
    empty = np.zeros(0, np.int64)
    if len(d1) == 0 or len(d2) < 2 or (mutual and len(d1) < 2):
        return empty, empty
    a, b = np.asarray(d1, np.float32), np.asarray(d2, np.float32)
    D = a @ b.T
    D *= -2.0
    D += np.einsum("ij,ij->i", a, a)[:, None]
    D += np.einsum("ij,ij->i", b, b)[None, :]
    np.maximum(D, 0.0, out=D)
    r2 = np.float32(ratio * ratio)                   # d0 < ratio d1 on squared distances
    fwd, f0, f1 = _two_nearest(D, 1)
    i1 = np.flatnonzero(f0 < r2 * f1)
    i2 = fwd[i1]
    if mutual and len(i1):
        back, b0, b1 = _two_nearest(D, 0)
        keep = (back[i2] == i1) & (b0[i2] < r2 * b1[i2])
        i1, i2 = i1[keep], i2[keep]
    return i1.astype(np.int64), i2.astype(np.int64)


def coarse_link(name_i: str, ov_i, name_j: str, ov_j, min_inliers: int = 12) -> CoarseLink | None:
    """Estimate a 2D affine map j -> i from overview features (xy full-res, desc)."""
    (xy_i, d_i), (xy_j, d_j) = ov_i, ov_j
    a, b = match_descriptors(d_i, d_j, 0.85, True)
    if len(a) < min_inliers:
        return None
    A, inl = cv2.estimateAffine2D(xy_j[b].astype(np.float32), xy_i[a].astype(np.float32),
                                  method=cv2.RANSAC, ransacReprojThreshold=30.0, maxIters=5000,
                                  confidence=0.999)
    if A is None or inl is None or int(inl.sum()) < min_inliers:
        return None
    inl = inl.ravel().astype(bool)
    res = xy_j[b][inl] @ A[:, :2].T + A[:, 2] - xy_i[a][inl]
    return CoarseLink(name_i, name_j, A.astype(np.float64), int(inl.sum()),
                      float(np.sqrt(np.mean(np.sum(res ** 2, axis=1)))))


def tile_overlap_fraction(ti: Tile, tj: Tile, A_ji: np.ndarray) -> float:
    """Fraction of tile i's area covered by tile j mapped into image i (polygon intersection)."""
    pi = ti.corners().astype(np.float32)
    pj = affine.apply_affine_2d(A_ji, tj.corners()).astype(np.float32)
    area, _ = cv2.intersectConvexConvex(pi, pj)
    return float(area) / (ti.width * ti.height)


def overlapping_tile_pairs(tiles_i: list[Tile], tiles_j: list[Tile], A_ji: np.ndarray,
                           min_fraction: float = 0.05) -> list[tuple[Tile, Tile]]:
    return [(ti, tj) for ti in tiles_i for tj in tiles_j
            if tile_overlap_fraction(ti, tj, A_ji) >= min_fraction]


def guided_matches(fi: ImageFeatures, fj: ImageFeatures, A_ji: np.ndarray, tiles_i: list[Tile],
                   cfg: MatchingConfig, margin_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Match image i against image j, each feature only against those predicted near it.

    The coarse map A_ji predicts where j's features fall in i; image i is cut into square cells
    (side ~2 x margin) and each cell's features are matched (ratio test, mutual check) against
    the j features predicted inside the cell grown by the margin. Exact nearest neighbours,
    and the cost grows linearly with the image area instead of quadratically.
    """
    pred = affine.apply_affine_2d(A_ji, fj.xy)          # j's features in i's pixels
    if len(fi) == 0 or len(fj) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    cell = max(64.0, 2.0 * margin_px)
    lo = fi.xy.min(axis=0)
    ci = np.floor((fi.xy - lo) / cell).astype(np.int64)
    ncol = int(ci[:, 0].max()) + 1
    key_i = ci[:, 1] * ncol + ci[:, 0]
    order_j = np.argsort(pred[:, 0], kind="stable")
    px_sorted = pred[order_j, 0]
    pairs = []
    by_key = np.argsort(key_i, kind="stable")
    sorted_keys = key_i[by_key]
    cuts = np.flatnonzero(np.r_[True, sorted_keys[1:] != sorted_keys[:-1], True])
    for a0, b0 in zip(cuts[:-1], cuts[1:]):
        sel_i = by_key[a0:b0]
        r, c = divmod(int(key_i[sel_i[0]]), ncol)
        x0, y0 = lo[0] + c * cell - margin_px, lo[1] + r * cell - margin_px
        x1, y1 = x0 + cell + 2 * margin_px, y0 + cell + 2 * margin_px
        a, b = np.searchsorted(px_sorted, [x0, x1])
        cand = order_j[a:b]
        cand = cand[(pred[cand, 1] >= y0) & (pred[cand, 1] < y1)]
        if len(sel_i) < 1 or len(cand) < 2:
            continue
        ia, jb = match_descriptors(fi.desc[sel_i], fj.desc[cand], cfg.ratio, cfg.mutual)
        ia, jb = sel_i[ia], cand[jb]
        near = np.linalg.norm(pred[jb] - fi.xy[ia], axis=1) < margin_px
        pairs.append(np.stack([ia[near], jb[near]], axis=1))
    if not pairs:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    m = np.concatenate(pairs)
    # a j feature claimed by two i features (neighbouring cells) is ambiguous: drop it
    _, inv, cnt = np.unique(m[:, 1], return_inverse=True, return_counts=True)
    m = m[cnt[inv] == 1]
    return m[:, 0], m[:, 1]


def verify_by_tile_pairs(fi: ImageFeatures, fj: ImageFeatures, idx_i: np.ndarray, idx_j: np.ndarray,
                         tile_pairs: list[tuple[Tile, Tile]], cfg: MatchingConfig,
                         rng: np.random.Generator) -> tuple[np.ndarray, list[TilePairStats]]:
    """Keep the matches that are F_A inliers in at least one tile pair containing both ends."""
    xi, xj = fi.xy[idx_i], fj.xy[idx_j]
    verified = np.zeros(len(idx_i), bool)
    stats = []
    for ti, tj in tile_pairs:
        sel = np.flatnonzero(ti.contains(xi) & tj.contains(xj))
        if len(sel) < max(8, cfg.min_inliers // 2):
            continue
        ci, cj = xi[sel] - ti.centre, xj[sel] - tj.centre
        F, inl = affine.fa_ransac(ci, cj, thresh_px=cfg.fa_thresh_px, iters=cfg.fa_ransac_iters, rng=rng)
        if F is None or inl.sum() < cfg.min_inliers:
            continue
        res = affine.fa_residuals(F, ci[inl], cj[inl])
        par = affine.parallax_ratio(ci[inl], cj[inl])
        verified[sel[inl]] = True
        stats.append(TilePairStats(ti.id, tj.id, len(sel), int(inl.sum()), float(par),
                                   float(np.sqrt(np.mean(res ** 2)))))
    return verified, stats


def match_pair(fi: ImageFeatures, fj: ImageFeatures, link: CoarseLink, tiles_i: list[Tile],
               tiles_j: list[Tile], cfg: MatchingConfig, rng: np.random.Generator) -> PairMatches:
    """Guided matching of two images, verified per overlapping tile pair."""
    margin = max(60.0, 4.0 * link.residual_px + 30.0)
    idx_i, idx_j = guided_matches(fi, fj, link.A_ji, tiles_i, cfg, margin)
    tps = overlapping_tile_pairs(tiles_i, tiles_j, link.A_ji)
    ok, stats = verify_by_tile_pairs(fi, fj, idx_i, idx_j, tps, cfg, rng)
    return PairMatches(fi.image, fj.image, idx_i[ok], idx_j[ok], stats)
