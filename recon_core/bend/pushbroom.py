"""The per-image pushbroom model's family, the within-tile correction, and what a set of views can
see of a bend (shared by the sparse stage, the upgrade and the render-free harness).

The model (recon_core.bend.image_model explains it and ties tile cameras to it): to second
order in the affine frame X, with r, c an image's own row and column (its mean affine camera,
normalised),

    row(X) = a . [X, 1] + r * (s_r . X) + k_r r^3          + f_2 c^2 + f_3 c^3 + y r^2 c
    col(X) = b . [X, 1] + c * (s_c . X) + k_2 r^2 + k_3 r^3 + g_3 c^3           + z r^2 c

The last terms are the focal plane's: a real line array is not one straight, undistorted line
(its ends bowed by a fraction of a pixel to pixels, across-track lens distortion of pixels), and
its attitude drifts in yaw and in scale over the image. Without them, the family fitted this
project's own synthetic cameras (0.003-0.096 px RMS) but missed an independent simulator's
(omaha_3dates: 0.11-0.23 px RMS, 0.7 px at most), and every correction built on the model read
that miss as a bend of the structure and put it in (5 m peak to peak on a 0.56 km site); with
them, 0.001 px there. The price: in one image, the row's c^2 is exactly what a quadratic bend
of the structure shows of itself, so the bend is no longer seen through the images' models
(docs: "The image model and the bend").
"""

from __future__ import annotations

import numpy as np

from recon_core.geometry.enu_map import BendWarp


def _focal_plane(r: np.ndarray, c: np.ndarray, row: bool) -> np.ndarray:
    """The focal plane's terms (module docstring): in the row, a bowed line (c^2, c^3) and a
    yaw drift (r^2 c); in the column, across-track distortion (c^3) and a scale drift (r^2 c)."""
    if row:
        return np.column_stack([c ** 2, c ** 3, r * r * c])
    return np.column_stack([c ** 3, r * r * c])


STRAIGHT_LINE_TERMS = (8, 9)   # the row's and the column's terms before the focal plane's


def row_basis(X: np.ndarray, r: np.ndarray, c: np.ndarray, focal_plane: bool = True) -> np.ndarray:
    """Basis of the row equation at points X (n, 3, standardised) with normalised rows r and
    columns c (n,); without `focal_plane`, a straight line array's."""
    one = np.ones((len(X), 1))
    fp = _focal_plane(r, c, True) if focal_plane else np.zeros((len(X), 0))
    return np.hstack([X, one, r[:, None] * X, (r ** 3)[:, None], fp])


def col_basis(X: np.ndarray, r: np.ndarray, c: np.ndarray, focal_plane: bool = True) -> np.ndarray:
    """Basis of the column equation (see the module docstring)."""
    one = np.ones((len(X), 1))
    fp = _focal_plane(r, c, False) if focal_plane else np.zeros((len(X), 0))
    return np.hstack([X, one, c[:, None] * X, (r ** 2)[:, None], (r ** 3)[:, None], fp])


def col_basis_known_depth(X: np.ndarray, r: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Basis of the column equation when the 1D perspective's term is known by physics and
    taken out of the pixels (estimate_bend's `depth`): what is left free is the affine part, the
    along-track terms r^2, r^3 and the range's change along the orbit, c r."""
    one = np.ones((len(X), 1))
    return np.hstack([X, one, (r ** 2)[:, None], (r ** 3)[:, None], (c * r)[:, None], _focal_plane(r, c, False)])


# -- the within-tile correction ---------------------------------------------------------------
# What drives the bend is the pushbroom's departure from affine inside each tile: an affine tile
# camera cannot reproduce it, and a smooth warp of the structure that makes every image's
# projection a little more affine on every tile lowers the reprojection error (the data prefer
# the bend: docs: research-notes.md, "What the views can see"). The tie only restricts the tile
# cameras; the observations still carry that departure. The correction removes the departure from the observations instead:
# each image's model is fitted to its observations, and every observation is moved by the
# model's own departure from its best affine approximation over the observation's tile,
#     corr = model(X) - A_t [X, 1],        pixel seen by the affine tile camera = xy - corr,
# so that an affine camera per tile sees affine data and nothing pushes the structure into a
# bend. It is a pixel field of a few tenths of a pixel (0.17 px RMS on omaha_3dates). Nothing
# holds the bends the views cannot see (warp_observability: through models of real focal
# planes, none), so a correction refitted again and again would let the structure wander along
# them with the points' noise (each refit takes the last displacement as the new reference):
# the SfM refits it only in its closing adjustments (SfmConfig.correction_rounds).

# an image with fewer tiles among the observations is too small a part of the image to fit its
# model: it gets no within-tile correction
MIN_TILES_FOR_CORRECTION = 4


def _image_coords(X: np.ndarray, xy: np.ndarray):
    """An image's observations xy (K, 2) of points X (K, 3) in the model's normalised terms:
    (mean affine camera (2, 4), X normalised (K, 3), r and c normalised (K,), the mean camera's
    pixels (K, 2) and their centre (2,))."""
    Xh = np.hstack([X, np.ones((len(X), 1))])
    mean_cam = np.linalg.lstsq(Xh, xy, rcond=None)[0].T
    x0 = X.mean(0)
    xs = float(np.sqrt(((X - x0) ** 2).sum(1).mean())) or 1.0
    uv = Xh @ mean_cam.T
    p0 = uv.mean(0)
    ps = float(np.sqrt(((uv - p0) ** 2).sum(1).mean())) or 1.0
    return mean_cam, (X - x0) / xs, (uv[:, 1] - p0[1]) / ps, (uv[:, 0] - p0[0]) / ps, uv, p0


def image_model_values(X: np.ndarray, xy: np.ndarray, trim: float = 4.0,
                       focal_plane: bool = True) -> np.ndarray:
    """(K, 2) the image model (module docstring) fitted by least squares to observations xy
    (K, 2: col, row) of points X (K, 3) in one image, evaluated at X. One refit without the
    observations beyond `trim` times the RMS residual (outliers the SfM has not dropped yet).
    On flat ground the model's basis is rank-deficient (r X and r^2 nearly collinear): the fitted
    values are still unique (minimum-norm least squares)."""
    _, Xn, r, c, _, _ = _image_coords(X, xy)
    bases = (col_basis(Xn, r, c, focal_plane), row_basis(Xn, r, c, focal_plane))
    keep = np.ones(len(X), bool)
    out = np.empty_like(xy, dtype=np.float64)
    for _ in range(2):
        for k, B in enumerate(bases):
            theta = np.linalg.lstsq(B[keep], xy[keep, k], rcond=None)[0]
            out[:, k] = B @ theta
        res = np.sqrt(((out - xy) ** 2).sum(1))
        rms = float(np.sqrt(np.mean(res[keep] ** 2)))
        new_keep = res <= max(trim * rms, 1e-9)
        if new_keep.all() or new_keep.sum() < 0.5 * len(X) or (new_keep == keep).all():
            break
        keep = new_keep
    return out


# -- does the family explain an image? -----------------------------------------------------------
# Every correction built on the image model (the tie, the within-tile correction, the bend step)
# assumes it explains each image to a few hundredths of a pixel; where it does not (a sensor whose
# focal plane, drift or scanning lies outside the family), the model's own error would be read as
# a bend of the structure and put into it. So the model's fit is checked on the run's own data:
# the residuals of each image's model, averaged over cells of the image, are the model's
# systematic error (the observations' noise averages out: its share, sigma^2 / n per cell, is
# taken off). Measured on true cameras (bench/bench_image_model.py): this family fits this
# project's synthetic pushbroom images to 0.003-0.096 px RMS and omaha_3dates' independent ones
# to 0.001 px; without its focal-plane terms, omaha_3dates' to 0.11-0.23 px.
MISFIT_CELLS = 6             # cells per image side, at most (fewer on images with few points:
MISFIT_CELL_POINTS = 30      # at least this many observations per cell on average)
MAX_STRAIGHT_MISFIT_PX = 0.02  # ... and a sensor whose straight-line model's is larger (once the
                             # bend it sees is out) is not a straight line array (the bend step's)
MAX_FOCAL_SHARE = 0.8        # unless the focal-plane terms take away less than this share of that
                             # misfit's power: the miss is then mostly not a focal plane's
                             # (omaha_3dates: 0.55-0.98 taken away, 0.98 on its worst image;
                             # this project's `large`, whose true cameras both families fit to
                             # under 0.01 px, leaves 0.03-0.11 px on the run's structure, of which
                             # they take away 0.33-0.60)
MAX_MODEL_MISFIT_PX = 0.1    # an image whose model's systematic error is larger is not explained
                             # (the straight-line family missed omaha_3dates' images by 0.03-0.17
                             # px on its structure; the focal-plane family fits them to 0.005-0.02
                             # px, and a small site's 2-view groups to 0.03-0.08 px)


def model_misfit(X: np.ndarray, xy: np.ndarray, cells: int = MISFIT_CELLS, trim: float = 4.0,
                 focal_plane: bool = True) -> float:
    """The systematic error (px, RMS over the image's cells) of the image model fitted to
    observations xy (K, 2) of points X (K, 3) in one image (see above); without `focal_plane`,
    of a straight line array's model."""
    cells = int(np.clip(np.sqrt(len(X) / MISFIT_CELL_POINTS), 2, cells))
    fit = image_model_values(X, xy, trim=trim, focal_plane=focal_plane)
    res = xy - fit
    size = np.sqrt((res ** 2).sum(1))
    keep = size <= trim * max(float(np.sqrt(np.mean(size ** 2))), 1e-9)
    res, pix = res[keep], xy[keep]
    lo, hi = pix.min(0), pix.max(0)
    ij = np.clip(((pix - lo) / np.maximum(hi - lo, 1e-9) * cells).astype(np.int64), 0, cells - 1)
    cell = ij[:, 1] * cells + ij[:, 0]
    n = np.bincount(cell, minlength=cells * cells).astype(np.float64)
    ok = n >= 10
    if not ok.any():
        return 0.0
    mean = np.stack([np.bincount(cell, res[:, a], minlength=cells * cells) for a in range(2)], 1) / np.maximum(n, 1)[:, None]
    var = (np.bincount(cell, (res ** 2).sum(1), minlength=cells * cells) / np.maximum(n, 1)
           - (mean ** 2).sum(1))
    # the mean of n residuals of variance var carries var / n of noise
    sys2 = (mean[ok] ** 2).sum(1) - var[ok] / n[ok]
    return float(np.sqrt(max(np.average(sys2, weights=n[ok]), 0.0)))


def affine_departure(X: np.ndarray, v: np.ndarray, group: np.ndarray, n_groups: int) -> np.ndarray:
    """(K, 2) v minus its least-squares affine fit in X within each group (a tile): v (K, 2)
    values at points X (K, 3), group (K,) in 0..n_groups-1. Nearly coplanar points leave the fit
    along their normal undetermined; the fitted values are still unique (pseudo-inverse)."""
    cnt = np.bincount(group, minlength=n_groups).astype(np.float64)
    w = 1.0 / np.maximum(cnt, 1.0)
    mu = np.stack([np.bincount(group, X[:, a], minlength=n_groups) for a in range(3)], 1) * w[:, None]
    vm = np.stack([np.bincount(group, v[:, a], minlength=n_groups) for a in range(2)], 1) * w[:, None]
    Xc, vc = X - mu[group], v - vm[group]
    S = np.empty((n_groups, 3, 3))
    R = np.empty((n_groups, 3, 2))
    for a in range(3):
        for b in range(a, 3):
            S[:, a, b] = S[:, b, a] = np.bincount(group, Xc[:, a] * Xc[:, b], minlength=n_groups)
        for b in range(2):
            R[:, a, b] = np.bincount(group, Xc[:, a] * vc[:, b], minlength=n_groups)
    B = np.linalg.pinv(S, rcond=1e-12, hermitian=True) @ R
    return vc - np.einsum("ka,kab->kb", Xc, B[group])


def tile_corrections(X: np.ndarray, xy: np.ndarray, tile: np.ndarray, img: np.ndarray,
                     min_tiles: int = MIN_TILES_FOR_CORRECTION) -> tuple[np.ndarray, dict]:
    """The within-tile correction of observations (see above): X (K, 3) the point of each
    observation, xy (K, 2) its pixel, tile (K,) and img (K,) its tile and image. Returns corr
    (K, 2), to be subtracted from xy before an affine tile camera sees it (zero in images with
    fewer than `min_tiles` tiles among the observations: too small a part of the image to fit its
    model), and a summary (images corrected, RMS and largest correction in px)."""
    corr = np.zeros((len(X), 2))
    done = []
    for i in np.unique(img):
        k = np.flatnonzero(img == i)
        tiles, local = np.unique(tile[k], return_inverse=True)
        if len(tiles) < min_tiles:
            continue
        model = image_model_values(X[k], xy[k])
        corr[k] = affine_departure(X[k], model, local.ravel(), len(tiles))
        done.append(int(i))
    return corr, {"images": done, **correction_size(corr)}


def correction_size(corr: np.ndarray) -> dict:
    """RMS and largest length (px) of corrections corr (K, 2); 0 for none."""
    size = np.sqrt((corr ** 2).sum(1))
    return {"rms_px": float(np.sqrt(np.mean(size ** 2))) if len(size) else 0.0,
            "max_px": float(size.max()) if len(size) else 0.0}


# -- what the views can see of a bend ------------------------------------------------------------
WARP_MONOMIALS = ("e^2", "e n", "n^2")


def warp_observability(X: np.ndarray, images: list[tuple[np.ndarray, np.ndarray]],
                       fixed_depth: list[np.ndarray] | None = None) -> dict:
    """How well a set of images sees each smooth quadratic warp of a structure when every image
    is a pushbroom of this module's family (its cameras free within the family, as the tie
    allows): for X (N, 3) metric points of nearly flat ground (e, n horizontal, u up) and, per
    image, (point indices, pixels (k, 2)), the warps X += q_a m(e, n) (a: e, n or u; m: e^2,
    e n, n^2, with e and n scaled to +-1 over the points) move each image's pixels by M_i q_a m
    (its mean affine camera); what the image model can re-fit (least squares over its basis at
    the points) is invisible. Returns the singular values of the remaining pixel motion per
    metre of warp (RMS px over all observations, largest first) and the warps (9-vectors over
    (a, m), a-major) they belong to: a warp with a singular value near zero changes nothing the
    images record, so no adjustment can find it; 4 GCPs do not either (they fix an affine map).

    fixed_depth: per image, the 1D perspective's coefficient s_c (3,) of `col_basis` known in
    this frame (c * (s_c . X)), instead of free: the column can then re-fit only what the drift
    and the along-track range change (c r) allow."""
    e0, n0 = X[:, 0].mean(), X[:, 1].mean()
    half = max(np.ptp(X[:, 0]), np.ptp(X[:, 1])) / 2.0 or 1.0
    e, n = (X[:, 0] - e0) / half, (X[:, 1] - n0) / half
    mono = np.stack([e * e, e * n, n * n], 1)                 # (N, 3)
    blocks = []
    for i, (pts, xy) in enumerate(images):
        S = X[pts]
        P, Xn, r, c, uv, p0 = _image_coords(S, xy)            # P: the mean affine camera
        if fixed_depth is None:
            Bc = col_basis(Xn, r, c)
        else:
            Bc = col_basis_known_depth(Xn, r, c)
        bases = (Bc, row_basis(Xn, r, c))
        motion = np.empty((len(S), 2, 9))                      # px per metre of each warp (a, m)
        for a in range(3):
            for m in range(3):
                d = np.zeros_like(S)
                d[:, a] = mono[pts, m]
                motion[:, :, 3 * a + m] = d @ P[:, :3].T
                if fixed_depth is not None:
                    # the known 1D perspective moves with the points: c * (s_c . d)
                    motion[:, 0, 3 * a + m] += (uv[:, 0] - p0[0]) * (d @ fixed_depth[i])
        # what each image's model cannot re-fit, column then row
        blocks.append(np.vstack([motion[:, k] - B @ np.linalg.lstsq(B, motion[:, k], rcond=None)[0]
                                 for k, B in enumerate(bases)]))
    Rm = np.vstack(blocks)
    U, s, Vt = np.linalg.svd(Rm, full_matrices=False)
    k = Rm.shape[0] / 2.0                                      # observations
    return {"singular_px_per_m": (s / np.sqrt(k)).tolist(), "warps": Vt, "half_width_m": float(half),
            "centre_m": [float(e0), float(n0)],
            "labels": [f"{ax} {m}" for ax in "enu" for m in WARP_MONOMIALS]}


EARTH_RADIUS_M = 6.371e6     # the mean Earth radius: the orbit geometry of the 1D perspective


def physical_depth(P: np.ndarray, altitude_m: float) -> np.ndarray:
    """The 1D perspective's coefficient s (3,) of a pushbroom whose mean affine camera in a
    metric ENU frame is P (2, 4): the column's offset from its centre scales as 1 / range, so a
    point dX nearer the satellite moves the column by (u_c - p_c)(s . dX) with s = -v / R, v the
    unit viewing direction (down) and R the slant range from an orbit of the given altitude
    (spherical Earth) at that zenith angle. The along-track direction has no perspective."""
    v = np.cross(P[0, :3], P[1, :3])
    v = v / np.linalg.norm(v)
    v = -v if v[2] > 0 else v
    cz = -v[2]
    R = -EARTH_RADIUS_M * cz + np.sqrt((EARTH_RADIUS_M * cz) ** 2 + 2 * EARTH_RADIUS_M * altitude_m
                                       + altitude_m ** 2)
    return -v / R


# -- the visible quadratic warp of a structure, estimated (the metric bend step's estimator) ----
# A quadratic warp of the structure moves each image's pixels in a way its model can only partly
# re-fit (warp_observability). The warp is estimated directly, by linear least squares over all images at once: the pixels'
# residual against every image's model fitted to the structure, explained by the motion each
# warp leaves once every model has re-fitted. Only warps the views see are estimated: a warp
# whose remaining motion is a small share of all it moves (the horizontal projective pair on
# many views; the vertical warps on one pass's 3 views) would be found from the models' own
# error, not from the data.
#
# The frame is affine (no metre exists before the upgrade), so the warps are measured in
# pixels: the frame is whitened by the images' mean cameras (a displacement of 1 unit in any
# direction moves the images by 1 px RMS), the ground plane's coordinates e, n by their spread,
# and the 9 warps are X += q_a m with m in (e^2, sqrt(2) e n, n^2) (a canonical family whatever
# the affine frame; not orthonormal over the points: their Gram matrix on `large` has a
# diagonal of 1.8-1.9). Their singular values are then shares (px of motion no model can re-fit
# per unit of warp, in px), the same in every affine frame.

MIN_POINTS_PER_IMAGE = 50   # an image with fewer distinct points is left out of the estimate
                            # (its model and its mean camera, which whitens the frame, would be
                            # fitted to too little: the model has 11 terms per equation)
MIN_WARP_SHARE = 0.02   # a warp is estimated when at least this share of the pixel motion it
                        # causes is beyond what every image's model can re-fit (below it, the
                        # warp would be found from the models' own error, not from the data).
                        # Through models of real focal planes no quadratic warp of an affine
                        # frame reaches it (every share < 0.01 on `large`'s 9 views): only the
                        # metric bend step, with each image's depth known, finds one


def _orthonormal(B: np.ndarray) -> np.ndarray:
    """Orthonormal basis of the columns of B (rank-revealing: on flat ground the model's basis
    is rank-deficient)."""
    U, s, _ = np.linalg.svd(B, full_matrices=False)
    return U[:, s > 1e-9 * s[0]] if len(s) and s[0] > 0 else U[:, :0]


def estimate_bend(X: np.ndarray, images: list[tuple[np.ndarray, np.ndarray]],
                  min_share: float = MIN_WARP_SHARE, trim: float = 4.0,
                  chunk: int = 200_000,
                  depth: list[np.ndarray | None] | None = None,
                  range_free: bool = False,
                  directions: np.ndarray | None = None,
                  pair: np.ndarray | None = None,
                  focal_plane: bool = True) -> tuple[BendWarp, dict]:
    """The visible quadratic warp of structure X (N, 3, any affine frame) that removes what the
    images' models cannot fit (see above), from each image's observations (point indices into
    X, pixels (k, 2): each point once per image; images with fewer than MIN_POINTS_PER_IMAGE
    points are left out, and with fewer than 2 left nothing is estimated). Add warp(X) to X to
    unbend it. Observations
    beyond `trim` times an image equation's RMS residual are left out (outliers). Returns the
    warp and a summary: the warps' singular values (shares, largest first), how many were
    estimated, the residual RMS (px), and the warp's size: the RMS over the points of the pixel
    motion it causes (whitened units). Each image's equations are read `chunk` observations at a
    time (_unexplained): memory is bounded whatever the image's size.

    depth: per image (aligned with `images`), the 1D perspective's coefficient s (3,) in X's
    frame when physics knows it (physical_depth, carried into X's frame by the upgrade), else
    None: the column's model is then col = b . [X, 1] + (u_c - p_c)(s . X) + k_2 r^2 + k_3 r^3
    + k_4 c r (u_c the mean camera's column, p_c its mean; c r: the range's change along the
    orbit), the known term taken out of the pixels and moved with the warp. What the free
    depth term absorbed (the horizontal projective pair) is then seen.
    range_free: with `depth`, one more unknown, a common relative change of every known depth
    (the orbit's altitude, assumed, is then only a start: the summary's "range_change" k says
    the data's depths are (1 + k) times the given ones). Its "share" is px of motion per unit
    of relative change, an absolute measure that grows with the site, not a share of its own
    motion as the warps' are. A change per image instead would
    absorb the projective pair again (tried: docs: research-notes.md, "The metric bend step").
    focal_plane: False models each image as a straight line array (the bend step's family: only
    there does a bend show through the models, and only sensors that are straight lines allow it).
    directions: (k, 3) the displacement directions in X's frame the warp may take (e.g. the
    upgrade's east and north: a horizontal warp only); default any.
    pair: with two `directions`, (2, 3) the linear functions of X that are the ground
    coordinates along them (the upgrade's rows for east and north): only the projective pair of
    that plane is then estimated, D = (g_1, g_2) (a . g) for the two unit vectors a (its
    quadratic part; g = pair X), the two warps an affine frame's free depths hide."""
    depths: list[np.ndarray | None] = [None] * len(images) if depth is None else list(depth)
    if len(depths) != len(images):
        raise ValueError("depth: one entry per image")
    kept = [k for k, (p, _) in enumerate(images) if len(p) >= MIN_POINTS_PER_IMAGE]
    images, depths = [images[k] for k in kept], [depths[k] for k in kept]
    if len(images) < 2:
        return BendWarp(X.mean(0), np.eye(3), np.zeros((2, 3)), np.zeros(3), np.zeros(9)), {
            "images": len(images), "warp_shares": [], "warps_seen": 0, "residual_rms_px": 0.0,
            "range_change": 0.0,
            "warp_rms_px": 0.0}
    nu = 10 if range_free else 9
    warp, cams, mono, Tinv = _whitened_frame(X, images)
    N, b, K, rss = _bend_equations(X, images, depths, cams, mono, Tinv, nu, trim, chunk, focal_plane)
    C = _warp_unknowns(X, warp, directions, pair, nu)
    coef, seen, share = _visible_warps(N, b, C, K, min_share, nu)
    range_change = float(coef[9]) if nu == 10 else 0.0
    coef = coef[:9]
    warp.coef = coef
    moved = float(np.sqrt(np.mean(((mono @ coef.reshape(3, 3).T) ** 2).sum(1))))
    return warp, {"images": len(images), "warp_shares": share.tolist(), "warps_seen": int(seen.sum()),
                  "residual_rms_px": float(np.sqrt(rss / max(K, 1))), "warp_rms_px": moved,
                  "range_change": range_change}


def _whitened_frame(X: np.ndarray, images: list) -> tuple[BendWarp, list, np.ndarray, np.ndarray]:
    """The frame the warps are estimated in: X whitened by the images' mean camera rows (T), its
    best plane with unit spread on each axis, and the warps' monomials over the points:
    (a zero BendWarp in that frame, each image's camera rows, the monomials (N, 3), T^-1)."""
    cams = [_image_coords(X[p], xy)[0][:, :3] for p, xy in images]
    M = np.vstack(cams)
    lam, V = np.linalg.eigh(M.T @ M / len(cams))
    T = (V * np.sqrt(np.maximum(lam, 1e-300))) @ V.T
    x0 = X.mean(0)
    Xw = (X - x0) @ T.T
    w0 = Xw.mean(0)
    _, sp, Vp = np.linalg.svd(Xw - w0, full_matrices=False)
    S = Vp[:2] / np.maximum(sp[:2, None] / np.sqrt(len(X)), 1e-12)   # unit spread on each plane axis
    warp = BendWarp(x0, T, S, w0, np.zeros(9))
    p = warp._plane(X)
    mono = np.stack([p[:, 0] ** 2, np.sqrt(2.0) * p[:, 0] * p[:, 1], p[:, 1] ** 2], 1)
    return warp, cams, mono, np.linalg.inv(T)


def _bend_equations(X: np.ndarray, images: list, depth: list, cams: list, mono: np.ndarray, Tinv: np.ndarray,
                    nu: int, trim: float, chunk: int, focal_plane: bool) -> tuple[np.ndarray, np.ndarray, int, float]:
    """The normal equations (N, b) of the nu warp unknowns once every image's model is eliminated
    (_unexplained, by chunks), with the observations used (K) and their residual sum of squares."""
    N, b, K, rss = np.zeros((nu, nu)), np.zeros(nu), 0, 0.0
    for (pts, xy), P3, s_i in zip(images, cams, depth):
        _, Xn, r, c, uv, p0 = _image_coords(X[pts], xy)
        M3 = P3 @ Tinv
        if s_i is not None:
            s_i = np.asarray(s_i, np.float64)
            du = uv[:, 0] - p0[0]                          # the column's offset (px)
            sx = (X[pts] - X[pts].mean(0)) @ s_i           # the known relative depth
            y = xy.astype(np.float64).copy()
            y[:, 0] -= du * sx
            sT = s_i @ Tinv
        for k in range(2):
            def rows(sl, k=k):
                """[model basis | motion of the 9 warps (and the range) | pixel] of observations sl: the pixel
                motion of each warp is the whitened displacement q_a m through the mean camera
                (and, with a known depth, through the 1D perspective it moves with)."""
                if k == 1:
                    B = row_basis(Xn[sl], r[sl], c[sl], focal_plane)
                elif s_i is None:
                    B = col_basis(Xn[sl], r[sl], c[sl], focal_plane)
                else:
                    B = col_basis_known_depth(Xn[sl], r[sl], c[sl])
                motion = np.einsum("km,a->kam", mono[pts[sl]], M3[k]).reshape(-1, 9)
                if s_i is None:
                    if nu == 10:
                        motion = np.hstack([motion, np.zeros((len(sl), 1))])
                    return np.hstack([B, motion, xy[sl, k:k + 1]])
                if k == 0:
                    # d[(u_c - p_c)(s . X)] = (M_c . D)(s . X) + (u_c - p_c)(s . D)
                    motion = motion * (1.0 + sx[sl, None]) + np.einsum(
                        "km,a->kam", mono[pts[sl]] * du[sl, None], sT).reshape(-1, 9)
                if nu == 10:
                    motion = np.hstack([motion, (du[sl] * sx[sl] if k == 0 else 0.0 * sx[sl])[:, None]])
                return np.hstack([B, motion, y[sl, k:k + 1]])
            Nk, bk, rk, nk = _unexplained(rows, len(pts), trim, chunk, nu)
            N += Nk
            b += bk
            rss += rk
            K += nk
    return N, b, K, rss


def _warp_unknowns(X: np.ndarray, warp: BendWarp, directions: np.ndarray | None, pair: np.ndarray | None,
                   nu: int) -> np.ndarray:
    """C: the warp coefficients (and the range change) as functions of the unknowns estimated,
    coef = C q: one per (direction, monomial), each direction of unit whitened length; with
    `pair`, only the projective pair of its plane (estimate_bend's docstring)."""
    T, x0, p = warp.T, warp.x0, warp._plane(X)
    # the unknowns: coef = C q, q per (direction, monomial), each direction of unit whitened length
    dirs = np.eye(3) if directions is None else np.asarray(directions, np.float64) @ T.T
    if pair is not None and len(dirs) != 2:
        raise ValueError("pair: needs the two directions of its plane")
    # each direction of unit whitened length; for the pair one common length, so that both
    # axes keep the pair's common factor (g_j (a . g) on each)
    norm = np.linalg.norm(dirs, axis=1, keepdims=True)
    dirs = dirs / (norm.mean() if pair is not None else norm)
    C = np.zeros((nu, 3 * len(dirs) + nu - 9))
    for j, dj in enumerate(dirs):
        for m in range(3):
            C[3 * np.arange(3) + m, 3 * j + m] = dj
    if nu == 10:
        C[9, -1] = 1.0
    if pair is not None:
        # g = L p + c over the points; the pair's quadratic part in p, per direction, as the
        # coefficients of (p1^2, sqrt2 p1 p2, p2^2)
        g = (X - x0) @ np.asarray(pair, np.float64).T
        L = np.linalg.lstsq(np.hstack([p, np.ones((len(p), 1))]), g, rcond=None)[0][:2].T
        Q = np.zeros((3 * len(dirs) + nu - 9, 2 + nu - 9))
        for k in range(2):
            for j in range(2):
                F = np.outer(L[j], L[k])                    # g_j g_k as a form in p
                F = (F + F.T) / 2.0
                Q[3 * j:3 * j + 3, k] = [F[0, 0], np.sqrt(2.0) * F[0, 1], F[1, 1]]
        if nu == 10:
            Q[-1, -1] = 1.0
        C = C @ Q
        C[:, :2] /= np.maximum(np.linalg.norm(C[:, :2], axis=0), 1e-300)
    return C


def _visible_warps(N: np.ndarray, b: np.ndarray, C: np.ndarray, K: int, min_share: float,
                   nu: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The warps the images see (their share of the pixel motion at least min_share), solved in
    that subspace: (coef (nu,), which were seen, every share, largest first)."""
    lam, V = np.linalg.eigh(C.T @ N @ C)
    lam, V = lam[::-1], V[:, ::-1]
    share = np.sqrt(np.maximum(lam, 0.0) / max(K / 2.0, 1.0))  # px per px of motion, per observation
    seen = share >= min_share
    coef = C @ (V[:, seen] @ ((V[:, seen].T @ (C.T @ b)) / lam[seen]))
    if not np.isfinite(coef).all():                 # a degenerate structure: nothing estimated
        coef, seen = np.zeros(nu), np.zeros(nu, bool)
    return coef, seen, share


def _stacked_r(rows, n: int, chunk: int, keep: np.ndarray | None = None) -> np.ndarray:
    """R of the QR decomposition of the n x m matrix whose rows rows(sl) gives, read by chunks of
    `chunk` rows (and only the rows in `keep`): the R of each chunk stacked under the R so far
    and decomposed again (a tall-skinny QR). R^T R is the whole matrix's Gram matrix, and
    least-squares projections on its columns are those on the whole matrix's columns."""
    R: np.ndarray | None = None
    for s0 in range(0, n, chunk):
        sl = np.arange(s0, min(s0 + chunk, n))
        if keep is not None:
            sl = sl[keep[sl]]
        if not len(sl):
            continue
        A = rows(sl)
        # (numpy's stubs give qr a QRResult whatever the mode; mode "r" returns R alone)
        R = np.linalg.qr(A if R is None else np.vstack([R, A]), mode="r")  # pyright: ignore[reportAssignmentType]
    assert R is not None                     # n > 0 rows kept
    return R


def _unexplained(rows, n: int, trim: float, chunk: int, nw: int = 9) -> tuple[np.ndarray, np.ndarray, float, int]:
    """One equation (column or row) of one image in the bend estimate: rows(sl) gives
    [basis (p) | warp motions (nw: 9, or 10 with the range) | pixel (1)] of observations sl.
    The model (the basis) is fitted to the pixels; observations beyond `trim` times its RMS residual are left out; of
    the rest, what the model cannot fit of the warps' motion (J) and of the pixels (res).
    Returns J^T J, J^T res, res^T res and the number of observations kept. Read by chunks
    (_stacked_r): the same figures as from the whole matrix, in bounded memory."""
    R = _stacked_r(rows, n, chunk)
    p = R.shape[1] - nw - 1
    theta = _lstsq_r(R[:, :p], R[:, -1:])[:, 0]
    res2 = np.empty(n)
    for s0 in range(0, n, chunk):
        A = rows(np.arange(s0, min(s0 + chunk, n)))
        res2[s0:s0 + len(A)] = (A[:, -1] - A[:, :p] @ theta) ** 2
    keep = res2 <= trim ** 2 * max(float(np.mean(res2)), 1e-24)
    R = _stacked_r(rows, n, chunk, keep)
    Q = _orthonormal(R[:, :p])
    rest = R[:, p:] - Q @ (Q.T @ R[:, p:])               # what the model cannot fit: [J | res]
    G = rest.T @ rest
    return G[:nw, :nw], G[:nw, nw], float(G[nw, nw]), int(keep.sum())


def _lstsq_r(Rb: np.ndarray, Ry: np.ndarray) -> np.ndarray:
    """Least-squares coefficients of columns Ry on the columns of Rb (rank-revealing, as
    _orthonormal: the minimum-norm solution on flat ground's rank-deficient basis)."""
    U, s, Vt = np.linalg.svd(Rb, full_matrices=False)
    on = s > 1e-9 * s[0] if len(s) and s[0] > 0 else np.zeros(len(s), bool)
    return Vt[on].T @ ((U[:, on].T @ Ry) / s[on, None])
