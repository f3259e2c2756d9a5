"""One physical camera model per image, tying the affine cameras of its tiles (the scale issue).

Why. Each tile has its own 8-parameter affine camera. A smooth bend W of the structure (a dome,
a saddle) is then almost free: every tile camera can follow it with a change that is linear in
the tile's position, P_t o W^-1 ~ P_t (I - J_W(X_t)), and the pushbroom's departure from affine
inside each tile (~0.2 px at d = 1000) is what pushes the adjustment into it (docs/research-notes.md,
"The image model and the bend"). 4 GCPs remove only the affine part of the bend.

The model. A pushbroom image is a line array swept in time: the points imaged at one row (one
instant) lie on a plane, and along that line the column is a 1D perspective. With smooth
attitude and orbit, to second order in the affine frame X of the reconstruction, with r, c the
image's own row and column (its mean affine camera, normalised):

    row(X) = a . [X, 1] + r * (s_r . X) + k_r r^3 + (the focal plane: c^2, c^3, r^2 c)
    col(X) = b . [X, 1] + c * (s_c . X) + k_2 r^2 + k_3 r^3 + (the focal plane: c^3, r^2 c)

r * (s_r . X): the instantaneous view plane turns while it sweeps (agile steering, pitch and yaw
rates), so the row is a ratio of affine functions of X; c * (s_c . X): the 1D perspective
across track (the depth of a point changes the column in proportion to its distance from the
centre); k r^2, k r^3: slow attitude drift in roll and pitch. The family is closed under 3D
affine maps of the frame (r, c follow the cameras), so the gauge stays the 12-dof affine one.
On this project's synthetic cameras (orbit, Earth rotation, agile steering, attitude drift),
the model fits the true projection of whole images of 5000-8192 px to 0.003-0.096 px RMS
(`bench/bench_image_model.py`), where a single affine camera is off by 0.4-3.6 px RMS and a
general quadratic in X by 0.06-0.9 px. The focal plane's terms (recon_core.bend.pushbroom:
a bowed, distorted line array, yaw and scale drifting) make it fit an independent simulator's
cameras too (omaha_3dates: 0.11-0.23 px RMS without them, 0.001 px with them).

A bend. A dome z += k (x^2 + y^2) moves image i by A_i[:, z] k (x^2 + y^2). Without the focal
plane's terms, its across-track part (x^2 ~ c^2) was visible in the row of every image with
along-track parallax; a bowed line is exactly such a c^2, so with them no image shows a bend
through its model, and no correction can read one there.

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
views: closing.tie_sigma; bench/bench_bend.py tries others). Each tile counts as 8 points (the
corners of its volume), whatever its number of observations.

Status (2026-11-27): off by default (SfmConfig.tie_sigma_px = 0). With the model's focal-plane
terms, which a real sensor needs, a bend of the structure is inside the model's family in every
image (the row's c^2 is what a bowed line makes): the tie no longer holds a bend, and on every
reference it left the DSM as it was (docs: accuracy.md). It stays an option; it stands aside for
an image its model does not explain (pushbroom.model_misfit).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from recon_core.bend.pushbroom import col_basis, row_basis  # the model's family


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
        G_row.append(E @ F @ row_basis(Xn, r, c))
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
