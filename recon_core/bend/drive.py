"""How far the structure may be bent where the views cannot see a bend: the size the sensors'
own departures from affine drive it to.

Why a structure bends (docs: research-notes.md, "What bends one date"). An affine tile camera
cannot follow its image's departure from affine inside the tile (the attitude's drift, a bowed
line, the 1D perspective), and a smooth warp of the structure that makes every tile a little
more affine lowers the reprojection error: the adjustment settles where the departures the
tiles cannot follow are least. Each image's row and column carry three independent quadratic
terms of their own (a drift in pitch or roll, r^2; a bowed line or distortion, c^2; a drift in
yaw, r c), so every quadratic warp of the structure can be taken up by the images, and none is
seen (recon_core.bend.observability). Where the structure settles is then set by the sensors'
departures themselves: the warp that best cancels them all at once.

What this module measures. In the metric frame the upgrade gives, each image's quadratic
departure from affine over its points (px at its ends: the 6 coefficients of r^2, r c, c^2 in
row and column, `e`), and what each of the 9 quadratic warps of the structure (1 m at the
site's edge) does to those coefficients (`P`, px per m). If the sensors' departures are
independent of one another and of the scene, the structure's warp is a least-squares estimate
from them, and the part of `e` no warp explains measures their spread: sigma^2 = |e - P w|^2 /
dof, and the warp's covariance is sigma^2 (P'P)^-1. The vertical warp's standard deviation,
less what the GCPs' affine map takes (its constant and tilt), is the expected bend.

Measured against the truth (render-free, `bench/bench_bend.py --drive`, 2026-11-28): on `flat`
and `flatfp`, seeds 0-2, the expected vertical bend was 0.65-4.3 times the actual (actual
quadratic U RMS 0.34-2.66 m): one bend is one draw, so this is its order of magnitude. It is a
size to expect, not a correction: moving the structure to the least-squares warp would put it
where the departures' spread, not the truth, says.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from recon_core.geometry.affine import apply_affine_3d

MIN_POINTS = 50          # an image with fewer points is left out (its 4 + 3 terms per equation)
MAX_PER_IMAGE = 20000    # points per image read (a random subset beyond: the fit is linear)


@dataclass(frozen=True)
class BendDrive:
    """The bend the views cannot see, as large as the sensors' departures drive it (module
    docstring).

    Attributes:
        views: images used.
        departure_px: RMS of the images' quadratic departures from affine (px at their ends).
        spread_px: their spread no warp of the structure explains (sigma, px).
        dof: degrees of freedom of that spread.
        expected_rms_m: expected vertical bend, RMS over the points, beyond an affine map.
        expected_edge_m: the same at the point where it is largest (the site's edge).
    """

    views: int
    departure_px: float
    spread_px: float
    dof: int
    expected_rms_m: float
    expected_edge_m: float

    def to_dict(self) -> dict:
        return {"views": self.views, "departure_px": self.departure_px, "spread_px": self.spread_px,
                "dof": self.dof, "expected_rms_m": self.expected_rms_m,
                "expected_edge_m": self.expected_edge_m,
                "meaning": "the vertical bend (m, beyond an affine map) to expect where the views "
                           "cannot see one: the images' quadratic departures from affine that no "
                           "warp of the structure explains, carried through the warps' least "
                           "squares (its order of magnitude: 0.65-4.3 times the actual on synthetic sites)"}


def _quadratic_basis(xy: np.ndarray) -> np.ndarray:
    """r^2, r c, c^2 of pixels (k, 2: col, row), each scaled to +-1 over their extent."""
    c = xy[:, 0] - xy[:, 0].mean()
    r = xy[:, 1] - xy[:, 1].mean()
    c = c / (np.abs(c).max() or 1.0)
    r = r / (np.abs(r).max() or 1.0)
    return np.column_stack([r * r, r * c, c * c])


def _image_terms(Y: np.ndarray, xy: np.ndarray, mono: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One image's quadratic departure from affine (6,: column r^2, r c, c^2, then row) and
    what each of the 9 warps (E, N, U x the site's monomials `mono` (k, 3)) does to it (6, 9),
    over its points Y (k, 3, metric) and pixels xy (k, 2)."""
    Yh = np.hstack([Y, np.ones((len(Y), 1))])
    B = np.hstack([Yh, _quadratic_basis(xy)])
    cam = np.linalg.lstsq(Yh, xy, rcond=None)[0].T                  # the mean affine camera
    e = np.linalg.lstsq(B, xy, rcond=None)[0][4:]                   # (3, 2)
    # warp (a, m) moves the pixels by cam[:, a] * mono[:, m] (px per m of E, N or U)
    W = (cam[None, :, :3, None] * mono[:, None, None, :]).reshape(len(Y), 2, 9)
    P = np.linalg.lstsq(B, W.reshape(len(Y), 18), rcond=None)[0][4:].reshape(3, 2, 9)
    return e.T.ravel(), P.transpose(1, 0, 2).reshape(6, 9)


def bend_drive(model, H: np.ndarray, seed: int = 0) -> BendDrive | None:
    """The expected vertical bend of a sparse model in the metric frame H (4, 4) gives (module
    docstring), each image's points once (at most MAX_PER_IMAGE); None with fewer than 2 images
    of MIN_POINTS points, or no degree of freedom."""
    ids = model.point_ids()
    if len(ids) < 100:
        return None
    slot = np.full(len(model.X), -1, np.int64)
    slot[ids] = np.arange(len(ids))
    rng = np.random.default_rng(seed)
    o = model.obs
    images = []
    for _, k in model.views_per_image(min_points=MIN_POINTS):
        if len(k) > MAX_PER_IMAGE:
            k = np.sort(rng.choice(k, MAX_PER_IMAGE, replace=False))
        images.append((slot[o.track[k]], o.xy[k]))
    return expected_bend(apply_affine_3d(H, model.X[ids]), images)


def expected_bend(Y: np.ndarray, images: list[tuple[np.ndarray, np.ndarray]]) -> BendDrive | None:
    """The expected vertical bend of metric points Y (N, 3) seen by images [(point indices,
    pixels (k, 2))] (module docstring); None with fewer than 2 images of MIN_POINTS points, or
    no degree of freedom."""
    centre = Y[:, :2].mean(0)
    half = float(np.abs(Y[:, :2] - centre).max()) or 1.0
    en = (Y[:, :2] - centre) / half
    mono = np.column_stack([en[:, 0] ** 2, en[:, 0] * en[:, 1], en[:, 1] ** 2])
    E, P = [], []
    for p, xy in images:
        if len(p) < MIN_POINTS:
            continue
        e, Pi = _image_terms(Y[p], xy, mono[p])
        E.append(e)
        P.append(Pi)
    if len(E) < 2:
        return None
    e_all, P_all = np.concatenate(E), np.vstack(P)
    U, s, _ = np.linalg.svd(P_all, full_matrices=False)
    rank = int(np.sum(s > 1e-9 * s[0])) if len(s) and s[0] > 0 else 0
    dof = len(e_all) - rank
    if dof <= 0:
        return None
    Ur = U[:, :rank]
    left = e_all - Ur @ (Ur.T @ e_all)
    sigma2 = float(left @ left) / dof
    C = sigma2 * np.linalg.pinv(P_all.T @ P_all)
    Cu = C[6:, 6:]                                                   # the vertical warps'
    # what an affine map (the GCPs') takes of each vertical warp: its constant and tilt
    A = np.column_stack([np.ones(len(en)), en])
    m_free = mono - A @ np.linalg.lstsq(A, mono, rcond=None)[0]
    var = np.einsum("ki,ij,kj->k", m_free, Cu, m_free)
    return BendDrive(views=len(E), departure_px=float(np.sqrt(np.mean(e_all ** 2))),
                     spread_px=float(np.sqrt(sigma2)), dof=int(dof),
                     expected_rms_m=float(np.sqrt(var.mean())),
                     expected_edge_m=float(np.sqrt(var.max())))
