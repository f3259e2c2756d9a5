"""One physical camera model per image, tying the affine cameras of its tiles (the scale issue).

Why. Each tile has its own 8-parameter affine camera. A smooth bend W of the structure (a dome,
a saddle) is then almost free: every tile camera can follow it with a change that is linear in
the tile's position, P_t o W^-1 ~ P_t (I - J_W(X_t)), and the pushbroom's departure from affine
inside each tile (~0.2 px at d = 1000) is what pushes the adjustment into it (GEOMETRY_NOTES,
"Tying tile cameras"). 4 GCPs remove only the affine part of the bend.

The model. A pushbroom image is a line array swept in time: the points imaged at one row (one
instant) lie on a plane, and along that line the column is a 1D perspective. With smooth
attitude and orbit, to second order in the affine frame X of the reconstruction, with r, c the
image's own row and column (its mean affine camera, normalised):

    row(X) = a . [X, 1] + r * (s_r . X) + k_r r^3
    col(X) = b . [X, 1] + c * (s_c . X) + k_2 r^2 + k_3 r^3

r * (s_r . X): the instantaneous view plane turns while it sweeps (agile steering, pitch and yaw
rates), so the row is a ratio of affine functions of X; c * (s_c . X): the 1D perspective
across track (the depth of a point changes the column in proportion to its distance from the
centre); k r^2, k r^3: slow attitude drift in roll and pitch. The family is closed under 3D
affine maps of the frame (r, c follow the cameras), so the gauge stays the 12-dof affine one.
On this project's synthetic cameras (orbit, Earth rotation, agile steering, attitude drift),
the model fits the true projection of whole images of 5000-8192 px to 0.003-0.096 px RMS
(`bench/bench_image_model.py`), where a single affine camera is off by 0.4-3.6 px RMS and a
general quadratic in X by 0.06-0.9 px.

What it cannot absorb: a bend. A dome z += k (x^2 + y^2) moves image i by A_i[:, z] k (x^2 +
y^2); in the row equation only products with r are allowed, so its across-track part (x^2, ~c^2)
is visible in every image with along-track parallax, in proportion to that parallax. Its
along-track part (y^2 ~ r^2) can still be absorbed by the drift terms: that direction stays
weakly determined, but nothing drives it once the model fits the pushbroom.

How it enters the adjustment. Per tile t, the model's best affine approximation over the tile's
points is linear in the model parameters theta: L_t theta. The tie residual is the difference
between the tile camera and that approximation, evaluated at the tile's points:
e_t = [S_t, 1] (P_t - L_t theta). theta is eliminated in closed form (least squares), leaving a
quadratic penalty 1/2 w p^T Q p on the stacked tile parameters p of the image, with
Q = D^T (I - Pi) D. Q couples every tile of the image with every other (a dense block of
(8 x tiles)^2, 415 MB for 900 tiles), so it is kept in factors: a block per tile minus a term of
rank <= 17 (the eliminated theta), which the dense bundle adjustment expands and the
block-sparse one solves by the Woodbury identity (`Tie`). Its weight w = (sigma_obs /
sigma_tie)^2: sigma_obs the observations' noise (measured from the reprojection error),
sigma_tie the model's error against a true pushbroom (SfmConfig.tie_sigma_px and the number of
views: sfm.tie_sigma; bench/bench_bend.py tries others). Each tile counts as 8 points (the
corners of its volume), whatever its number of observations.

Status: the tie holds every closing global adjustment of the SfM. It discriminates (the truth
costs 0.01 px against the model, a bent solution 0.03-0.12 px) and holds a joint adjustment of
9 views (`large`: bend 4.6 -> 1.1 m peak to peak), but on a group of 3 views the bend moves
inside the model's family (README, "What was tried against the bend"). What the views can see
of a bend at all is `warp_observability` below; what drives it is removed by the within-tile
correction (`tile_corrections`), in the closing adjustments after the first.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Tie:
    """The penalty 1/2 * p^T Q p on the flat camera entries p = cams.reshape(-1)[idx] of one
    image's n tiles (tile-major, 8 entries each), kept in factored form. For each image
    coordinate (entries 0-3 of a tile: column, 4-7: row), with E the weighted values of each
    tile's affine parameters at its sample points (rows of tile t: `E[row_tile == t]`) and B an
    orthonormal basis of the model's family at those rows:

        Q = E^T (I - B B^T) E = blockdiag(DtD) - L L^T,  DtD_t = E_t^T E_t,  L_t = E_t^T B_t.

    The cost and gradient are evaluated as residuals, e = E p - B (B^T E p): 1/2 |e|^2 and E^T e
    (a difference of the two squared terms loses every digit when the cameras are in the
    model's family: pixel values of 10^4 against a departure of 10^-4). Q itself is a dense
    (8n)^2 matrix (`dense_q`): fine for a few hundred tiles, 415 MB for an image of 900 tiles;
    the block-sparse adjustment uses DtD (a block on each tile's own diagonal) and L (a low-rank
    term per image: the eliminated model parameters)."""

    idx: np.ndarray                         # (8 n,) indices into the flat (T * 8) camera array
    E: np.ndarray                           # (R, 4) sqrt(w) [S, 1] * tile weight, all samples
    row_tile: np.ndarray                    # (R,) tile (0..n-1) of each row, non-decreasing
    B: tuple[np.ndarray, np.ndarray]        # per coordinate (column, row): (R, k_c), orthonormal
    DtD: np.ndarray                         # (n, 4, 4)
    L: tuple[np.ndarray, np.ndarray]        # per coordinate: (n, 4, k_c)

    def _residuals(self, flat: np.ndarray) -> list[np.ndarray]:
        p = flat[self.idx].reshape(-1, 2, 4)
        out = []
        for coord, B in enumerate(self.B):
            e = np.einsum("rj,rj->r", self.E, p[self.row_tile, coord])
            out.append(e - B @ (B.T @ e))
        return out

    def grad(self, flat: np.ndarray) -> np.ndarray:
        """Q p (8 n,)."""
        n = len(self.DtD)
        g = np.empty((n, 2, 4))
        for coord, e in enumerate(self._residuals(flat)):
            for j in range(4):
                g[:, coord, j] = np.bincount(self.row_tile, self.E[:, j] * e, minlength=n)
        return g.reshape(-1)

    def cost(self, flat: np.ndarray) -> float:
        return 0.5 * float(sum(e @ e for e in self._residuals(flat)))

    def diag(self) -> np.ndarray:
        """The diagonal of Q (8 n,)."""
        n = len(self.DtD)
        d = np.empty((n, 2, 4))
        for coord, L in enumerate(self.L):
            d[:, coord] = np.einsum("tii->ti", self.DtD) - np.einsum("tjk,tjk->tj", L, L)
        return d.reshape(-1)

    def dense_q(self) -> np.ndarray:
        """Q as a dense (8 n, 8 n) matrix."""
        n = len(self.DtD)
        Q = np.zeros((8 * n, 8 * n))
        for coord, B in enumerate(self.B):
            sel = (8 * np.arange(n)[:, None] + 4 * coord + np.arange(4)[None, :]).ravel()
            # (I - B B^T) E tile by tile as columns of one (R, 4 n) matrix
            D = np.zeros((len(self.E), 4 * n))
            D[np.arange(len(self.E))[:, None], 4 * self.row_tile[:, None] + np.arange(4)] = self.E
            R = D - B @ (B.T @ D)
            Q[np.ix_(sel, sel)] = R.T @ R
        return 0.5 * (Q + Q.T)


def row_basis(X: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Basis of the row equation at points X (n, 3, standardised) with normalised rows r (n,)."""
    one = np.ones((len(X), 1))
    return np.hstack([X, one, r[:, None] * X, (r ** 3)[:, None]])


def col_basis(X: np.ndarray, r: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Basis of the column equation (see the module docstring)."""
    one = np.ones((len(X), 1))
    return np.hstack([X, one, c[:, None] * X, (r ** 2)[:, None], (r ** 3)[:, None]])


def image_frame(cams: np.ndarray, samples: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, float, np.ndarray, float]:
    """The image's mean affine camera (2, 4) fitted to its tile cameras over their sample points,
    with the normalisation of X (mean, scale) and of pixels (centre, scale)."""
    S = np.concatenate(samples)
    uv = np.concatenate([s @ P[:, :3].T + P[:, 3] for s, P in zip(samples, cams)])
    Sh = np.hstack([S, np.ones((len(S), 1))])
    mean_cam = np.linalg.lstsq(Sh, uv, rcond=None)[0].T
    x0 = S.mean(0)
    xs = float(np.sqrt(((S - x0) ** 2).sum(1).mean())) or 1.0
    p0 = uv.mean(0)
    ps = float(np.sqrt(((uv - p0) ** 2).sum(1).mean())) or 1.0
    return mean_cam, x0, xs, p0, ps


def image_tie(cams: np.ndarray, samples: list[np.ndarray], tile_index: np.ndarray,
              weight: float) -> Tie:
    """The tie of one image's tiles: cams (n, 2, 4) their cameras, samples[t] (m_t, 3) points of
    tile t in the affine frame, tile_index (n,) their indices in the group's camera array."""
    mean_cam, x0, xs, p0, ps = image_frame(cams, samples)
    E_blocks, G_row, G_col = [], [], []
    for S in samples:
        Sh = np.hstack([S, np.ones((len(S), 1))])
        uv = Sh @ mean_cam.T
        r = (uv[:, 1] - p0[1]) / ps
        c = (uv[:, 0] - p0[0]) / ps
        Xn = (S - x0) / xs
        F = np.linalg.pinv(Sh)                       # (4, m): values at S -> affine parameters
        scale = np.sqrt(8.0 / max(len(S), 1))        # each tile weighs as 8 points
        E = Sh * scale                               # (m, 4): affine parameters -> values at S
        E_blocks.append(E)
        G_row.append(E @ F @ row_basis(Xn, r))
        G_col.append(E @ F @ col_basis(Xn, r, c))
    rows = np.cumsum([0] + [len(E) for E in E_blocks])
    row_tile = np.repeat(np.arange(len(E_blocks)), np.diff(rows))
    E_all = np.sqrt(weight) * np.vstack(E_blocks)
    DtD = np.stack([E_all[rows[t]:rows[t + 1]].T @ E_all[rows[t]:rows[t + 1]] for t in range(len(E_blocks))])
    Bs, Ls = [], []
    for G in (np.vstack(G_col), np.vstack(G_row)):
        B, s_, _ = np.linalg.svd(G, full_matrices=False)
        B = np.ascontiguousarray(B[:, s_ > s_[0] * 1e-10])
        Bs.append(B)
        Ls.append(np.stack([E_all[rows[t]:rows[t + 1]].T @ B[rows[t]:rows[t + 1]] for t in range(len(E_blocks))]))
    idx = (8 * np.asarray(tile_index, dtype=np.int64)[:, None] + np.arange(8)[None, :]).ravel()
    return Tie(idx, E_all, row_tile, (Bs[0], Bs[1]), DtD, (Ls[0], Ls[1]))


def tie_residual_px(tie_cams: np.ndarray, samples: list[np.ndarray]) -> float:
    """RMS (px) of the tile cameras' departure from the best-fitting image model over their
    samples, each tile weighing as 8 points (a diagnostic: what the tie costs)."""
    t = image_tie(tie_cams, samples, np.arange(len(tie_cams)), 1.0)
    p = tie_cams.reshape(-1)
    return float(np.sqrt(max(2 * t.cost(p), 0.0) / (16 * len(tie_cams))))


# -- the within-tile correction ---------------------------------------------------------------
# What drives the bend is the pushbroom's departure from affine inside each tile: an affine tile
# camera cannot reproduce it, and a smooth warp of the structure that makes every image's
# projection a little more affine on every tile lowers the reprojection error (the data prefer
# the bend: README, "What was tried against the bend"). The tie above only restricts the tile
# cameras; the observations still carry that departure, and on 3 views a bend inside the model's
# family still lowers it. The correction removes the departure from the observations instead:
# each image's model is fitted to its observations, and every observation is moved by the
# model's own departure from its best affine approximation over the observation's tile,
#     corr = model(X) - A_t [X, 1],        pixel seen by the affine tile camera = xy - corr,
# so that an affine camera per tile sees affine data and nothing pushes the structure into a
# bend. It is a pixel field of a few hundredths of a pixel (0.12 px at most on `flat`). Where the
# views see a warp (warp_observability), the adjustment then finds the unbent structure; where
# they do not (3 views of one kind: the vertical bends), nothing holds it, and a correction
# refitted again and again lets the structure wander along those warps with the points' noise
# (each refit takes the last displacement as the new reference). So the SfM refits it only in
# its closing adjustments, after the tie has held the structure once (SfmConfig.correction_rounds).

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


def image_model_values(X: np.ndarray, xy: np.ndarray, trim: float = 4.0) -> np.ndarray:
    """(K, 2) the image model (module docstring) fitted by least squares to observations xy
    (K, 2: col, row) of points X (K, 3) in one image, evaluated at X. One refit without the
    observations beyond `trim` times the RMS residual (outliers the SfM has not dropped yet).
    On flat ground the model's basis is rank-deficient (r X and r^2 nearly collinear): the fitted
    values are still unique (minimum-norm least squares)."""
    _, Xn, r, c, _, _ = _image_coords(X, xy)
    bases = (col_basis(Xn, r, c), row_basis(Xn, r))
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
    size = np.sqrt((corr ** 2).sum(1))
    return corr, {"images": done,
                  "rms_px": float(np.sqrt(np.mean(size ** 2))) if len(size) else 0.0,
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
            Bc = np.hstack([Xn, np.ones((len(S), 1)), (r * r)[:, None], (r ** 3)[:, None], (c * r)[:, None]])
        bases = (Bc, row_basis(Xn, r))
        cols = []
        for a in range(3):
            for m in range(3):
                d = np.zeros_like(S)
                d[:, a] = mono[pts, m]
                motion = d @ P[:, :3].T                        # (k, 2) px per metre of warp
                if fixed_depth is not None:
                    # the known 1D perspective moves with the points: c * (s_c . d)
                    motion[:, 0] += (uv[:, 0] - p0[0]) * (d @ fixed_depth[i])
                res = []
                for k, B in enumerate(bases):
                    theta = np.linalg.lstsq(B, motion[:, k], rcond=None)[0]
                    res.append(motion[:, k] - B @ theta)
                cols.append(np.concatenate(res))
        blocks.append(np.stack(cols, 1))
    Rm = np.vstack(blocks)
    U, s, Vt = np.linalg.svd(Rm, full_matrices=False)
    k = Rm.shape[0] / 2.0                                      # observations
    return {"singular_px_per_m": (s / np.sqrt(k)).tolist(), "warps": Vt, "half_width_m": float(half),
            "labels": [f"{ax} {m}" for ax in "enu" for m in WARP_MONOMIALS]}
