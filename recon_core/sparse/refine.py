"""Sub-pixel refinement of tie points by affine-warped least-squares patch matching.

SIFT places a keypoint at a scale-space extremum: on this project's images its position is off
by ~0.35-0.4 px per axis (measured against the true cameras on `large`). The depth of a point
seen from two views with base-to-height ratio b/h is off by that error times GSD / (b/h): the
sparse structure's noise is the keypoints' noise. Photogrammetric tie points are refined by
least-squares matching (LSM) instead: an observation is moved to where a small patch around
it, warped by the local affine map between the two images, best agrees (zero-mean normalised)
with the patch of a reference view of the same track (refine_tracks says which). The first
view's own offset only chooses which ground point the track follows, so it needs no
refinement.

The kernel is vectorised over patches: every Gauss-Newton iteration samples all patches with
one `cv2.remap` call per image (value and gradients) and solves one 2 x 2 system per patch.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from recon_core.io.site import read_window
from recon_core.sparse.features import ImageFeatures


@dataclass
class RefineResult:
    xy: np.ndarray          # (n, 2) refined target positions (the input where not accepted)
    ok: np.ndarray          # (n,) bool: the refined position was accepted
    ncc: np.ndarray         # (n,) final weighted zero-mean normalised correlation
    shift: np.ndarray       # (n,) distance moved, px


def _grid(half: int) -> tuple[np.ndarray, np.ndarray]:
    r = np.arange(-half, half + 1, dtype=np.float64)
    gx, gy = np.meshgrid(r, r)
    g = np.stack([gx.ravel(), gy.ravel()], 1)
    sigma = 0.5 * half + 0.5
    w = np.exp(-(g ** 2).sum(1) / (2 * sigma ** 2))
    return g, w / w.sum()


def _sample(img: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Bilinear samples of img at pts (n, G, 2) (x = column, y = row, pixel centres at
    integers); outside the image gives NaN."""
    n, G = pts.shape[:2]
    out = np.empty((n, G), np.float32)
    step = max(1, 30000 // max(G, 1))          # cv2.remap wants dst dimensions below 32767
    for s in range(0, n, step):
        p = pts[s:s + step].astype(np.float32)
        out[s:s + step] = cv2.remap(img, p[..., 0], p[..., 1], cv2.INTER_LINEAR,
                                    borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
    return out


def _normalise(v: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    m = v @ w
    c = v - m[:, None]
    s = np.sqrt(np.maximum((c * c) @ w, 1e-20))
    return c / s[:, None], m, s


def smooth(img: np.ndarray, sigma: float) -> np.ndarray:
    """The image as float32, NaN kept, lightly blurred so that its gradients are not noise."""
    a = np.asarray(img, np.float32)
    if sigma <= 0:
        return a
    bad = ~np.isfinite(a)
    b = cv2.GaussianBlur(np.where(bad, 0, a), (0, 0), sigma)
    if bad.any():
        b[cv2.dilate(bad.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0] = np.nan
    return b


def gradients(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Central differences along columns and rows (NaN on the border)."""
    gx = np.empty_like(img)
    gy = np.empty_like(img)
    gx[:, 1:-1] = 0.5 * (img[:, 2:] - img[:, :-2])
    gx[:, [0, -1]] = np.nan
    gy[1:-1] = 0.5 * (img[2:] - img[:-2])
    gy[[0, -1]] = np.nan
    return gx, gy


def refine_points(ref: np.ndarray, ref_xy: np.ndarray, tgt: np.ndarray, tgt_xy: np.ndarray,
                  A: np.ndarray, half: int = 7, iters: int = 8, min_ncc: float = 0.7,
                  max_shift: float = 1.5, min_texture: float = 1e-3,
                  tgt_grad: tuple[np.ndarray, np.ndarray] | None = None) -> RefineResult:
    """Move each tgt_xy to where the patch of `tgt` around it best matches the patch of `ref`
    around ref_xy, the target patch's grid being the reference grid mapped by A (2 x 2, or
    (n, 2, 2): d(target) = A d(reference)).

    Gauss-Newton on the two translation parameters of the zero-mean normalised difference, with
    a Gaussian window. A position is accepted only when the final correlation is >= min_ncc, it
    moved at most max_shift px, the last step was below 0.02 px and the patch has texture in
    both directions (smallest eigenvalue of the normal matrix, normalised, >= min_texture).
    `tgt_grad`: gradients(tgt), when the caller refines several sets against one target."""
    n = len(ref_xy)
    g, w = _grid(half)
    A = np.broadcast_to(np.asarray(A, np.float64), (n, 2, 2)) if np.ndim(A) == 2 else np.asarray(A)
    ref = np.asarray(ref, np.float32)
    tgt = np.asarray(tgt, np.float32)
    gx, gy = gradients(tgt) if tgt_grad is None else tgt_grad
    Rn, _, _ = _normalise(_sample(ref, ref_xy[:, None, :] + g[None]), w)
    gt = np.einsum("nij,gj->ngi", A, g)                    # target grid offsets (n, G, 2)
    p = np.asarray(tgt_xy, np.float64).copy()
    step = np.full(n, np.inf)
    lam_min = np.zeros(n)
    live = np.isfinite(Rn).all(1)
    for _ in range(iters):
        k = np.flatnonzero(live)
        if not len(k):
            break
        pts = p[k, None, :] + gt[k]
        T = _sample(tgt, pts)
        Jx = _sample(gx, pts)
        Jy = _sample(gy, pts)
        fin = np.isfinite(T).all(1) & np.isfinite(Jx).all(1) & np.isfinite(Jy).all(1)
        live[k[~fin]] = False  # pyright: ignore[reportIndexIssue]
        k, T, Jx, Jy = k[fin], T[fin], Jx[fin], Jy[fin]
        Tn, _, sT = _normalise(T, w)
        Jx = (Jx - (Jx @ w)[:, None]) / sT[:, None]
        Jy = (Jy - (Jy @ w)[:, None]) / sT[:, None]
        r = Tn - Rn[k]
        a, b, c = (Jx * Jx) @ w, (Jx * Jy) @ w, (Jy * Jy) @ w
        bx, by = (Jx * r) @ w, (Jy * r) @ w
        det = a * c - b * b
        tr = a + c
        lam_min[k] = 0.5 * (tr - np.sqrt(np.maximum(tr * tr - 4 * det, 0.0)))
        good = det > 1e-12
        dx = np.where(good, -(c * bx - b * by) / np.where(good, det, 1.0), 0.0)
        dy = np.where(good, -(a * by - b * bx) / np.where(good, det, 1.0), 0.0)
        d = np.stack([dx, dy], 1)
        big = np.hypot(dx, dy) > 0.5                       # damp: a GN step of a patch is local
        d[big] *= (0.5 / np.hypot(dx, dy)[big])[:, None]
        p[k] += d
        step[k] = np.hypot(d[:, 0], d[:, 1])
        live[k[~good]] = False  # pyright: ignore[reportIndexIssue]
        live[k[step[k] < 1e-3]] = False  # pyright: ignore[reportIndexIssue]
    # the correlation at the final position
    pts = p[:, None, :] + gt
    Tn, _, _ = _normalise(_sample(tgt, pts), w)
    fin = np.isfinite(Tn).all(1) & np.isfinite(Rn).all(1)
    ncc = np.where(fin, np.sum(np.where(fin[:, None], Tn * Rn, 0.0) * w, 1), -1.0)  # pyright: ignore[reportIndexIssue]
    shift = np.hypot(*(p - tgt_xy).T)
    ok = fin & (ncc >= min_ncc) & (shift <= max_shift) & (step < 0.02) & (lam_min >= min_texture)
    return RefineResult(np.where(ok[:, None], p, tgt_xy), ok, ncc, shift)


# -- the tracks of a group ---------------------------------------------------------------------
@dataclass
class TrackRefinement:
    """What refine_tracks did: counts over the non-reference observations of the tracks."""

    candidates: int = 0
    refined: int = 0
    median_shift_px: float = 0.0
    pairs: dict | None = None       # "ref|target" -> [candidates, refined]

    def summary(self) -> dict:
        return {"candidates": self.candidates, "refined": self.refined,
                "median_shift_px": round(self.median_shift_px, 3), "pairs": self.pairs or {}}


def _linear_map(P: np.ndarray, Q: np.ndarray) -> np.ndarray | None:
    """The 2 x 2 linear part of the 2D affine map P -> Q, robust to relief parallax (one
    refit without the residuals above 3 medians)."""
    if len(P) < 6:
        return None
    M = np.c_[P - P.mean(0), np.ones(len(P))]
    keep = np.ones(len(P), bool)
    for _ in range(2):
        C = np.linalg.lstsq(M[keep], Q[keep], rcond=None)[0]
        r = np.hypot(*(M @ C - Q).T)
        keep = r <= 3 * max(np.median(r), 0.5)
        if keep.sum() < 6:
            return None
    return C[:2].T


def _first_of(key: np.ndarray, img: np.ndarray) -> np.ndarray:
    """For every node, the node of the same key (track, or track and date group) in the
    lowest-numbered image."""
    order = np.lexsort((img, key))
    first = np.ones(len(order), bool)
    first[1:] = key[order][1:] != key[order][:-1]
    ref = np.empty(len(key), np.int64)
    ref[order] = order[np.maximum.accumulate(np.where(first, np.arange(len(order)), 0))]
    return ref


def refine_tracks(images, feats, tracks, *, image_groups=None, half: int = 7, min_ncc: float = 0.7,
                  sigma: float = 0.7, block: int = 2048, max_shift: float = 1.5):
    """Refine the keypoints of every track by refine_points, each against a view of the same
    date (same radiometry, shadows and vegetation): within a date group, every observation
    against the group's first view of the track; the first view of each other group against
    the track's first view (before the others, so that they follow it). `image_groups`: the
    date group of each image (None: one group). Images are read by window, one block of each
    target image at a time. Returns (new features, TrackRefinement); a feature belongs to at
    most one track, so each refined keypoint is moved in its own image's features."""
    img, feat, trk = tracks.img, tracks.feat, tracks.track
    stats = TrackRefinement(pairs={})
    if not len(trk):
        return feats, stats
    grp = np.zeros(len(img), np.int64) if image_groups is None else np.asarray(image_groups)[img]
    track_first = _first_of(trk, img)
    group_first = _first_of(trk * (int(grp.max()) + 1) + grp, img)
    pos = np.zeros((len(trk), 2))          # the nodes' positions, refined in place
    for k, f in enumerate(feats):
        s = img == k
        pos[s] = f.xy[feat[s]]
    nodes = np.arange(len(trk))
    across = (group_first == nodes) & (track_first != nodes)
    within = group_first != nodes
    shifts = []
    for sel, ref in ((across, track_first), (within, group_first)):
        shifts += _refine_pass(images, pos, np.flatnonzero(sel), ref, img, stats,
                               half=half, min_ncc=min_ncc, sigma=sigma, block=block, max_shift=max_shift)
    stats.candidates = int((across | within).sum())
    if shifts and sum(len(s) for s in shifts):
        stats.median_shift_px = float(np.median(np.concatenate(shifts)))
    out = []
    for k, f in enumerate(feats):
        s = img == k
        fx = f.xy.copy()
        fx[feat[s]] = pos[s]
        out.append(ImageFeatures(f.image, fx, f.desc, f.scale, f.response, f.gray))
    return out, stats


CHUNK = 20000       # points per refine_points call: its patch arrays stay ~100 MB


def _refine_pass(images, pos, todo, ref, img, stats, *, half, min_ncc, sigma, block, max_shift) -> list:
    """Refine nodes `todo` against nodes ref[todo] in place in `pos`; returns the moves kept."""
    shifts = []
    ma = half + 2 + int(np.ceil(4 * sigma)) + 2          # reference window margin (px)
    for b, imb in enumerate(images):
        nb = todo[img[todo] == b]
        if not len(nb):
            continue
        maps = {}
        for a in np.unique(img[ref[nb]]):
            s = nb[img[ref[nb]] == a]
            maps[int(a)] = _linear_map(pos[ref[s]], pos[s])
            stats.pairs.setdefault(f"{images[a].name}|{imb.name}", [0, 0])[0] += int(len(s))
        for r0 in range(0, imb.height, block):
            for c0 in range(0, imb.width, block):
                s_blk = nb[(pos[nb, 1] >= r0 - 0.5) & (pos[nb, 1] < r0 + block - 0.5)
                           & (pos[nb, 0] >= c0 - 0.5) & (pos[nb, 0] < c0 + block - 0.5)]
                if not len(s_blk):
                    continue
                groups = {int(a): s_blk[img[ref[s_blk]] == a] for a in np.unique(img[ref[s_blk]])}
                groups = {a: s for a, s in groups.items() if maps[a] is not None}
                if not groups:
                    continue
                reach = max(np.abs(maps[a]).sum(1).max() for a in groups)
                m = int(np.ceil(half * reach + max_shift + 2 + 4 * sigma)) + 2
                tc0, tr0 = max(0, c0 - m), max(0, r0 - m)
                tc1, tr1 = min(imb.width, c0 + block + m), min(imb.height, r0 + block + m)
                tgt = smooth(read_window(imb, tc0, tr0, tc1 - tc0, tr1 - tr0), sigma)
                grad = gradients(tgt)                  # once per window, for every reference
                for a, s in groups.items():
                    ima = images[a]
                    P = pos[ref[s]]
                    rc0 = max(0, int(np.floor(P[:, 0].min())) - ma)
                    rr0 = max(0, int(np.floor(P[:, 1].min())) - ma)
                    rc1 = min(ima.width, int(np.ceil(P[:, 0].max())) + ma + 1)
                    rr1 = min(ima.height, int(np.ceil(P[:, 1].max())) + ma + 1)
                    refw = smooth(read_window(ima, rc0, rr0, rc1 - rc0, rr1 - rr0), sigma)
                    for c in range(0, len(s), CHUNK):          # bounded patch arrays
                        sc = s[c:c + CHUNK]
                        res = refine_points(refw, pos[ref[sc]] - (rc0, rr0), tgt, pos[sc] - (tc0, tr0),
                                            maps[a], half=half, min_ncc=min_ncc, max_shift=max_shift,
                                            tgt_grad=grad)
                        pos[sc] = res.xy + (tc0, tr0)
                        stats.pairs[f"{ima.name}|{imb.name}"][1] += int(res.ok.sum())
                        stats.refined += int(res.ok.sum())
                        shifts.append(res.shift[res.ok])
    return shifts
