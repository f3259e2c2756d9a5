"""What the cameras say about the Euclidean frame: the rows of a satellite tile camera are
orthogonal in metres.

An affine tile camera x = M X + t (M: 2 x 3) of a narrow-field pushbroom has, in a Euclidean
frame, a row-gradient along the normal of the scan's view plane and a column-gradient inside
that plane (perpendicular to the ray), so its two rows are orthogonal up to the small drift of
the view direction during the scan. In the affine frame they are not: for an upgrade
X_E = A X + b the camera seen in metres is M A^-1, and the cosine between its rows,

    c(A) = m1' m2 / (|m1'| |m2'|),  [m1'; m2'] = M A^-1,

depends on A only through (A^T A)^-1: it is blind to rotation, isotropic scale and translation,
and sensitive exactly to what 4 nearly coplanar GCPs leave loose: the height scale and the
shear of height into easting and northing (a camera looking off-nadir has a vertical component
in its rows, and a wrong height scale tilts them).

Measured cosines (per image, the median over its tiles):
- synthetic pushbroom sites with agile steering, truth frame (the sparse structure's best affine
  map to the true points): |c| <= 1.2e-3, RMS 0.6e-3 (`large`, 9 images; `demo`, `flat`);
- real Pleiades pairs, in the frame of their 4 well-spread GCPs: -0.9e-3 and 1.8e-3 (La
  Reunion), -0.2e-3 and -0.5e-3 (Gizeh);
- the GCP-only upgrade of `large` (4 GCPs, 40 m of relief over 3 km): up to 3.3e-3, with a
  height scale 2.7 % short.
Hence SIGMA_COS = 2e-3 per image: the largest departure seen on real images. Each image adds one
equation with that sigma to the GCPs' 3N equations (sigma: the affine point's height
uncertainty), and H_A is the weighted least-squares solution of both.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from recon_core.geometry.affine import as_4x4, fit_affine_3d, normalize_points

SIGMA_COS = 2e-3          # per image: the largest departure seen on real images (see above)


@dataclass
class ImageRows:
    """The linear parts (k, 2, 3) of one image's registered tile cameras in the affine frame."""

    image: str
    M: np.ndarray


def camera_rows(model) -> list[ImageRows]:
    """Each image's registered tile cameras (linear parts), images with none left out."""
    by_image: dict[str, list[np.ndarray]] = {}
    for t in np.flatnonzero(model.registered):
        by_image.setdefault(model.tiles[t].image, []).append(np.asarray(model.cams[t])[:, :3])
    return [ImageRows(name, np.array(v)) for name, v in by_image.items()]


def row_cosines(A: np.ndarray, rows: list[ImageRows]) -> np.ndarray:
    """Per image, the median cosine between the rows of its tile cameras seen through the
    upgrade's linear part A (3 x 3): M A^-1."""
    Ai = np.linalg.inv(np.asarray(A, dtype=np.float64)[:3, :3])
    out = np.empty(len(rows))
    for k, r in enumerate(rows):
        Me = r.M @ Ai
        n1 = np.linalg.norm(Me[:, 0], axis=1)
        n2 = np.linalg.norm(Me[:, 1], axis=1)
        out[k] = np.median(np.sum(Me[:, 0] * Me[:, 1], axis=1) / np.maximum(n1 * n2, 1e-300))
    return out


def fit_with_metric_prior(X_aff: np.ndarray, X_enu: np.ndarray, sigma_m: float,
                          rows: list[ImageRows], sigma_cos: float = SIGMA_COS,
                          H0: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """H_A (4 x 4) minimising sum |H x_i - X_i|^2 / sigma_m^2 + sum_images c_k(A)^2 / sigma_cos^2.

    Solved in similarity-normalised coordinates (the cosines do not change under them) by
    Levenberg-Marquardt from the GCP-only fit (or H0). Returns (H, covariance of H[:3]'s 12
    entries, row by row, in metres)."""
    xa, Ta = normalize_points(X_aff)
    xe, Te = normalize_points(X_enu)
    s_e = Te[0, 0]                       # metres -> normalised units
    sig = max(float(sigma_m), 1e-6) * s_e
    if H0 is None:
        h0 = fit_affine_3d(xa, xe)
    else:
        h0 = (Te @ np.asarray(H0, dtype=np.float64) @ np.linalg.inv(Ta))[:3]

    def residuals(p):
        h = p.reshape(3, 4)
        r_g = (xa @ h[:, :3].T + h[:, 3] - xe).ravel() / sig
        return np.concatenate([r_g, row_cosines(h[:, :3], rows) / sigma_cos])

    sol = least_squares(residuals, h0.ravel(), method="lm", x_scale=1.0, xtol=1e-12, ftol=1e-12,
                        max_nfev=200)
    h = as_4x4(sol.x.reshape(3, 4))
    J = sol.jac
    cov = np.linalg.pinv(J.T @ J)
    return np.linalg.inv(Te) @ h @ Ta, _denormalised_cov(cov, Ta, Te)


def _denormalised_cov(cov: np.ndarray, Ta: np.ndarray, Te: np.ndarray) -> np.ndarray:
    """Covariance of H's 12 entries (rows of H[:3], metres) from that of the normalised map:
    H = Te^-1 h Ta is linear in h."""
    Tei = np.linalg.inv(Te)
    L = np.zeros((12, 12))
    for k in range(12):
        e = np.zeros((4, 4))
        e[k // 4, k % 4] = 1.0
        L[:, k] = (Tei @ e @ Ta)[:3].ravel()
    return L @ cov @ L.T


def gcp_only_cov(X_aff: np.ndarray, sigma_m: float) -> np.ndarray:
    """Covariance of H's 12 entries for the GCP-only least squares (isotropic sigma_m)."""
    D = np.c_[np.asarray(X_aff, dtype=np.float64), np.ones(len(X_aff))]
    C4 = np.linalg.pinv(D.T @ D) * sigma_m ** 2
    cov = np.zeros((12, 12))
    for r in range(3):
        cov[4 * r:4 * r + 4, 4 * r:4 * r + 4] = C4
    return cov


def height_sigma(H: np.ndarray, cov: np.ndarray, normal: np.ndarray, height_m: float) -> float:
    """Standard deviation (m) of the height, above the GCPs, of a point `height_m` above their
    plane (unit `normal` in ENU), from the covariance of H's entries: only the linear part
    acting on the affine direction of that offset counts."""
    d = np.linalg.solve(np.asarray(H, dtype=np.float64)[:3, :3], normal * height_m)   # affine offset
    g = np.zeros(12)
    g[8:11] = d                                    # d(U)/d(H[2, :3])
    return float(np.sqrt(max(g @ cov @ g, 0.0)))
