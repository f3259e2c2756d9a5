"""H_A held by the cameras: the control GCPs and the images' lines of sight in one weighted fit.

Four GCPs give H_A's 12 unknowns 12 equations and no redundancy: their noise goes straight into
what they fix worst, and on flat ground that is the height scale and the shear of height into
easting and northing (the column of H_A that maps the affine direction off the GCPs' plane).
The images know those directions: each image's line of sight in the affine frame, d, must map
onto its direction on the ground from the metadata, v (recon_core.euclidean.sight). This module
fits H_A to both, each weighted by what it knows:

- a control GCP: residual H_A x - X (metres), with covariance A S A^T + sigma_m^2 I, where S is
  the covariance of its affine point from its image observations (the triangulation's, with
  the pixel noise of the GCPs' own observations) and sigma_m its survey accuracy; with affine
  cameras this is exactly the fit that takes the GCPs' image observations as observations;
- an image: the two components of A d / |A d| across v (radians), with one sigma for all
  images, estimated from the fit's own residuals (variance component estimation, with
  SIGMA_VIEW_DEG as a prior worth PRIOR_DOF residuals) when the images are redundant.

The fit is linear in H_A (v x A d = 0 is), solved by least squares reweighted until the weights,
which depend on A, settle. Its covariance says what the GCPs and the images fix and leave
loose: `looseness` turns it into the height scale, shear and tilt errors to expect
(docs/accuracy.md, "Any 4 GCPs").

Measured on omaha_3dates' true cameras (the images' RPCs, for evaluation only): the lines of
sight of the tile cameras are 0.1-0.2 degrees from the true ones (the affine cameras fix their
response to height only as well as the relief lets them), the vendor's angles 0.01 degrees
from the truth; on the real Pleiades pairs 0.02-0.05 degrees. Hence the prior of 0.1 degrees.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from recon_core.geometry.affine import as_4x4, normalize_points
from recon_core.geometry.geodesy import LocalFrame

SIGMA_VIEW_DEG = 0.1    # prior sigma of an image's line of sight (tile cameras against the
                        # vendor's angles): 0.1-0.2 deg on omaha_3dates, 0.02-0.05 on real pairs
PRIOR_DOF = 4.0         # that prior weighs as much as this many residuals of the estimate
VIEW_FLOOR_DEG = 0.01   # no estimate below the vendor angles' own accuracy (0.01 deg)
PICK_SIGMA_M = 0.4      # a GCP picked on the cloud (no observations): its position's sigma per axis
RANK_REL = 1e-10        # eigenvalues of the normal matrix below this (relative) are not fixed


@dataclass
class ControlPoints:
    """The control GCPs a fit uses: affine points Xa (n, 3), surveyed ENU Xe (n, 3), each
    affine point's covariance S (n, 3, 3; NaN where unknown: a point picked on the cloud), survey
    sigma (n,) in metres, and the surveyed height's own sigma (n,; None: sigma_m's)."""

    Xa: np.ndarray
    Xe: np.ndarray
    S: np.ndarray
    sigma_m: np.ndarray
    sigma_h: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.sigma_h is None:
            self.sigma_h = np.asarray(self.sigma_m, np.float64).copy()

    @property
    def _sigma_h(self) -> np.ndarray:
        assert self.sigma_h is not None      # __post_init__ sets it
        return self.sigma_h

    def take(self, idx) -> "ControlPoints":
        return ControlPoints(self.Xa[idx], self.Xe[idx], self.S[idx], self.sigma_m[idx], self._sigma_h[idx])

    def __len__(self) -> int:
        return len(self.Xa)

    def cov_enu(self, H: np.ndarray | None) -> np.ndarray:
        """(n, 3, 3) each residual's covariance in metres through H's linear part."""
        n = len(self.Xa)
        out = np.empty((n, 3, 3))
        for i in range(n):
            if H is None or not np.all(np.isfinite(self.S[i])):
                out[i] = np.eye(3) * PICK_SIGMA_M ** 2
            else:
                A = H[:3, :3]
                out[i] = A @ self.S[i] @ A.T
            out[i] += np.diag([self.sigma_m[i] ** 2, self.sigma_m[i] ** 2, self._sigma_h[i] ** 2])
        return out


@dataclass
class HeldFit:
    """H_A fitted to control GCPs and lines of sight.

    Attributes:
        H: (4, 4) affine -> ENU.
        cov: the covariance of H[:3]'s entries, row by row (metres).
        normal: (12, 12) the fit's normal matrix in the same units (information).
        sigma_view_deg: the images' sigma the fit used (None without lines of sight).
        view_residual_deg: image -> angle between A d and its direction from the metadata.
        view_redundancy: how many of the images' equations the fit had to spare.
    """

    H: np.ndarray
    cov: Covariance
    normal: np.ndarray
    sigma_view_deg: float | None = None
    view_residual_deg: dict[str, float] = field(default_factory=dict)
    view_redundancy: float = 0.0


def _design(x: np.ndarray) -> np.ndarray:
    """(3, 12): d(H x~)/d(H[:3] row by row) for one point x (3,)."""
    D = np.zeros((3, 12))
    for k in range(3):
        D[k, 4 * k:4 * k + 3] = x
        D[k, 4 * k + 3] = 1.0
    return D


def _whitener(C: np.ndarray) -> np.ndarray:
    """W with W^T W = C^-1 (C symmetric positive semi-definite, 3 x 3; floored at 1 mm per axis
    so that a point known exactly along one axis does not break the factorisation)."""
    C = 0.5 * (C + C.T) + np.eye(3) * 1e-6
    return np.linalg.cholesky(np.linalg.inv(C)).T


def _across(v: np.ndarray) -> np.ndarray:
    """(2, 3): two unit vectors across the unit vector v."""
    a = np.array([0.0, 0.0, 1.0]) if abs(v[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(v, a)
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(v, e1)])


def _gcp_rows(pts: ControlPoints, H: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    C = pts.cov_enu(H)
    rows, rhs = [], []
    for i in range(len(pts)):
        W = _whitener(C[i])
        rows.append(W @ _design(pts.Xa[i]))
        rhs.append(W @ pts.Xe[i])
    return np.concatenate(rows).reshape(-1, 12), np.concatenate(rhs).reshape(-1)


def _view_rows(rays, dirs, H: np.ndarray | None, sigma_rad: float) -> np.ndarray:
    """(2 K, 12): the components of A d across v, over |A d| sigma (the angle in sigmas)."""
    out = []
    for ray, v in zip(rays, dirs):
        s = 1.0 if H is None else max(float(np.linalg.norm(H[:3, :3] @ ray.d)), 1e-300)
        E = _across(v)
        R = np.zeros((2, 12))
        for k in range(3):
            R[:, 4 * k:4 * k + 3] = E[:, k:k + 1] * ray.d[None]
        out.append(R / (s * sigma_rad))
    return np.concatenate(out).reshape(-1, 12) if out else np.zeros((0, 12))


def _solve(J: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Least squares with column scaling (the translation and linear entries differ by orders)."""
    scale = np.linalg.norm(J, axis=0)
    scale[scale == 0] = 1.0
    return np.linalg.lstsq(J / scale, b, rcond=None)[0] / scale


@dataclass
class Covariance:
    """The covariance of H[:3]'s 12 entries from a normal matrix that may not fix them all:
    `pinv` over what it fixes, `null` (12, k) the directions it does not (k = 0: all fixed)."""

    pinv: np.ndarray
    null: np.ndarray

    @classmethod
    def of(cls, N: np.ndarray) -> "Covariance":
        s = np.sqrt(np.maximum(np.diag(N), 1e-300))
        w, V = np.linalg.eigh(N / s[:, None] / s[None, :])
        ok = w > RANK_REL * max(float(w[-1]), 1e-300)
        pinv = (V[:, ok] / w[ok]) @ V[:, ok].T / s[:, None] / s[None, :]
        null = V[:, ~ok] / s[:, None]
        return cls(pinv, null / np.maximum(np.linalg.norm(null, axis=0), 1e-300))

    @property
    def determined(self) -> bool:
        return self.null.shape[1] == 0

    def variance(self, g: np.ndarray) -> float:
        """Variance of g . h (h: H[:3]'s entries); inf when g reaches what is not fixed."""
        if self.null.shape[1] and np.max(np.abs(g @ self.null)) > 1e-8 * max(float(np.linalg.norm(g)), 1e-300):
            return float("inf")
        return float(max(g @ self.pinv @ g, 0.0))


def fit_held(pts: ControlPoints, rays: list, frame: LocalFrame | None = None,
             sigma_view_deg: float = SIGMA_VIEW_DEG, estimate_sigma: bool = True,
             H0: np.ndarray | None = None, iters: int = 30) -> HeldFit:
    """H_A from control GCPs and lines of sight (module docstring).

    Args:
        pts: the control GCPs (>= 3 not on one line, or >= 4 not on one plane without rays).
        rays: recon_core.euclidean.sight.ViewRay per image (may be empty: the GCPs alone,
            weighted by their covariances).
        frame: the site's ENU frame (turns each image's direction into it; None: not turned).
        sigma_view_deg: the images' sigma, or its prior when estimate_sigma.
        H0: a start (default: the fit itself from unit weights).
    """
    sig = np.radians(sigma_view_deg)
    sig0 = sig
    H = None if H0 is None else np.asarray(H0, np.float64)
    red = 0.0
    for it in range(iters):
        dirs = [r.direction(frame, H) for r in rays]
        Jg, bg = _gcp_rows(pts, H)
        Jv = _view_rows(rays, dirs, H, sig)
        J = np.concatenate([Jg, Jv])
        b = np.concatenate([bg, np.zeros(len(Jv))])
        p = _solve(J, b)
        H_new = as_4x4(p.reshape(3, 4))
        changed = H is None or np.max(np.abs(H_new - H)) > 1e-9 * max(1.0, float(np.max(np.abs(H_new))))
        H = H_new
        sig_new = sig
        if rays and estimate_sigma and it >= 1:
            C = Covariance.of(J.T @ J)
            if C.determined:
                hat = np.einsum("ij,jk,ik->i", Jv, C.pinv, Jv)
                red = float(np.sum(1.0 - hat))
                ss = float(np.sum((Jv @ p * sig) ** 2))
                sig_new = max(np.radians(VIEW_FLOOR_DEG), np.sqrt((ss + PRIOR_DOF * sig0 ** 2) / (red + PRIOR_DOF)))
        if not changed and abs(sig_new - sig) <= 1e-6 * sig and it >= 2:
            break
        sig = sig_new
    assert H is not None                     # the loop ran
    dirs = [r.direction(frame, H) for r in rays]
    Jg, _ = _gcp_rows(pts, H)
    Jv = _view_rows(rays, dirs, H, sig)
    N = np.concatenate([Jg, Jv]).T @ np.concatenate([Jg, Jv])
    res = {}
    for r, v in zip(rays, dirs):
        u = H[:3, :3] @ r.d
        u /= np.linalg.norm(u)
        res[r.image] = float(np.degrees(np.arccos(min(1.0, abs(float(u @ v))))))
    return HeldFit(H=H, cov=Covariance.of(N), normal=N, sigma_view_deg=float(np.degrees(sig)) if rays else None,
                   view_residual_deg=res, view_redundancy=red)


def gcp_normal(pts: ControlPoints, H: np.ndarray) -> np.ndarray:
    """The GCPs' share of the normal matrix (their information on H_A) at H."""
    Jg, _ = _gcp_rows(pts, H)
    return Jg.T @ Jg


@dataclass
class Looseness:
    """What a fit leaves loose, as standard deviations (inf: not fixed at all).

    height_scale: of the height of a point above the GCPs, relative (0.01: 1 %);
    shear_E, shear_N: easting and northing error per metre of height;
    tilt_E, tilt_N: height error per metre east and north of the GCPs' centre;
    expected_height_error_m: height_scale times `structure_height_m`.
    """

    height_scale: float
    shear_E: float
    shear_N: float
    tilt_E: float
    tilt_N: float
    structure_height_m: float
    tilt_max: float = 0.0           # the tilt's sigma in its worst horizontal direction
    site_radius_m: float = 0.0      # how far the site reaches from the GCPs' centre

    @property
    def expected_height_error_m(self) -> float:
        return self.height_scale * self.structure_height_m

    @property
    def expected_edge_error_m(self) -> float:
        """The height error the tilt leaves at the site's edge (the worst direction)."""
        return self.tilt_max * self.site_radius_m

    def to_dict(self) -> dict:
        def f(x: float):
            return float(x) if np.isfinite(x) else None
        return {"height_scale_sigma": f(self.height_scale), "shear_sigma_E": f(self.shear_E),
                "shear_sigma_N": f(self.shear_N), "tilt_sigma_E": f(self.tilt_E),
                "tilt_sigma_N": f(self.tilt_N), "tilt_sigma_max": f(self.tilt_max),
                "structure_height_m": self.structure_height_m,
                "expected_height_error_m": f(self.expected_height_error_m),
                "site_radius_m": self.site_radius_m, "expected_edge_error_m": f(self.expected_edge_error_m)}


def looseness(H: np.ndarray, cov: Covariance, structure_height_m: float = 40.0,
              site_radius_m: float = 0.0) -> Looseness:
    """The height scale, shear and tilt sigmas of H_A from the covariance of its entries (and the
    height error the tilt leaves `site_radius_m` from the GCPs' centre)."""
    Ai = np.linalg.inv(np.asarray(H, np.float64)[:3, :3])

    def grad(out_axis: int, enu_dir: np.ndarray) -> np.ndarray:
        g = np.zeros(12)
        g[4 * out_axis:4 * out_axis + 3] = Ai @ enu_dir
        return g

    def sigma(out_axis: int, enu_dir: np.ndarray) -> float:
        return float(np.sqrt(cov.variance(grad(out_axis, enu_dir))))

    up, east, north = np.eye(3)[2], np.eye(3)[0], np.eye(3)[1]
    # the worst horizontal direction of the tilt: the largest of its 2 x 2 covariance's axes
    tilt = [sigma(2, east), sigma(2, north)]
    if all(np.isfinite(tilt)):
        gE, gN = grad(2, east), grad(2, north)
        c = cov.variance(gE + gN) - tilt[0] ** 2 - tilt[1] ** 2      # 2 cov(E, N)
        C = np.array([[tilt[0] ** 2, c / 2], [c / 2, tilt[1] ** 2]])
        tilt_max = float(np.sqrt(max(np.linalg.eigvalsh(C)[-1], 0.0)))
    else:
        tilt_max = float("inf")
    return Looseness(sigma(2, up), sigma(0, up), sigma(1, up), tilt[0], tilt[1],
                     float(structure_height_m), tilt_max, float(site_radius_m))
