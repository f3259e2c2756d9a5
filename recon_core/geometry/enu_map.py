"""The Euclidean upgrade of a group as one map: affine frame -> local ENU metres,
X -> Y + G(Y), Y = H_A (X + D(X)), D the metric bend step's warp (recon_core.bend.metric)
or none, G the bend fitted to control GCPs (recon_core.bend.gcp), or the vertical bend
taken from a reference DEM (recon_core.bend.dem), or none.
Shared by the upgrade stage that fits it, the files that record it and the DSM stage that
applies it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from recon_core.geometry.affine import apply_affine_3d


@dataclass
class BendWarp:
    """A quadratic warp X -> X + D(X) of an affine structure (its basis: recon_core.bend.pushbroom,
    estimate_bend): D(X) = T^-1 d,
    d_a = sum_m coef[3 a + m] mono_m(e, n), (e, n) = S (T (X - x0) - w0)."""
    x0: np.ndarray        # (3,) the structure's centre
    T: np.ndarray         # (3, 3) whitening of the frame by the mean cameras
    S: np.ndarray         # (2, 3) the ground plane's normalised coordinates in the whitened frame
    w0: np.ndarray        # (3,) the whitened centre
    coef: np.ndarray      # (9,) the warp, (axis a, monomial m), a-major, in whitened units (px)

    def _plane(self, X: np.ndarray) -> np.ndarray:
        return ((X - self.x0) @ self.T.T - self.w0) @ self.S.T

    def __call__(self, X: np.ndarray) -> np.ndarray:
        """(n, 3) the displacement D(X) of points X (n, 3)."""
        p = self._plane(X)
        mono = np.stack([p[:, 0] ** 2, np.sqrt(2.0) * p[:, 0] * p[:, 1], p[:, 1] ** 2], 1)
        return (mono @ self.coef.reshape(3, 3).T) @ np.linalg.inv(self.T).T

    def jacobian(self, X: np.ndarray) -> np.ndarray:
        """(n, 3, 3) dD/dX at points X (n, 3)."""
        p = self._plane(X)
        e, n = p[:, 0], p[:, 1]
        z = np.zeros_like(e)
        r2 = np.sqrt(2.0)
        dmono = np.stack([np.stack([2 * e, z], 1), np.stack([r2 * n, r2 * e], 1),
                          np.stack([z, 2 * n], 1)], 1)                 # (n, 3 monomials, 2)
        dd = np.einsum("am,nmk,kj->naj", self.coef.reshape(3, 3), dmono, self.S @ self.T)
        return np.einsum("ab,nbj->naj", np.linalg.inv(self.T), dd)


    def follow(self, cams: np.ndarray, centres: np.ndarray) -> np.ndarray:
        """(T, 2, 4) affine cameras cams (T, 2, 4) moved with the warp's linear part at their
        points' centres (T, 3), so that they still see the warped points where they saw them:
        X' = X + D(X) ~ c + D(c) + (I + G)(X - c) (G = dD/dX at c) gives A' = A (I + G)^-1 and
        p' = A c + p - A' (c + D(c)). What is left (the warp's curvature over a tile) is far
        below a pixel, and the next adjustment takes it."""
        A, p = cams[:, :, :3], cams[:, :, 3]
        A_new = np.einsum("tij,tjk->tik", A, np.linalg.inv(np.eye(3) + self.jacobian(centres)))
        p_new = (np.einsum("tij,tj->ti", A, centres) + p
                 - np.einsum("tij,tj->ti", A_new, centres + self(centres)))
        return np.concatenate([A_new, p_new[:, :, None]], 2)


def monomials(e: np.ndarray, n: np.ndarray, degree: int) -> np.ndarray:
    """(len(e), k) monomials of (e, n) of degree 2 to `degree`, by degree, then by falling power
    of e: e^2, e n, n^2 (degree 2), then e^3, e^2 n, e n^2, n^3, ..."""
    return np.stack([e ** (d - i) * n ** i for d in range(2, int(degree) + 1) for i in range(d + 1)], 1)


def n_monomials(degree: int) -> int:
    """How many monomials of degree 2 to `degree` there are."""
    return sum(d + 1 for d in range(2, int(degree) + 1))


def monomial_degree(k: int) -> int:
    """The degree D of which there are k monomials of degree 2 to D (ValueError if none)."""
    d = 2
    while n_monomials(d) < k:
        d += 1
    if n_monomials(d) != k:
        raise ValueError(f"{k} coefficients per axis are no polynomial warp's (3, 7, 12, ...)")
    return d


@dataclass
class EnuWarp:
    """A polynomial displacement of local ENU positions: D(Y) = sum_a,m coef[k a + m] mono_m(e, n)
    along axis a (E, N, U), mono the k monomials of degree 2 to `degree` (e^2, e n, n^2, then
    e^3, e^2 n, ...: `monomials`), e = (E - centre_E) / half, n likewise. The degree follows from
    the number of coefficients (9: quadratic, as the GCP and metric bends; 21: cubic)."""

    centre: np.ndarray    # (2,) E, N (m)
    half: float           # m
    coef: np.ndarray      # (3 k,) m at e, n = +-1, a-major

    @property
    def degree(self) -> int:
        n = len(np.ravel(self.coef))
        if n % 3:
            raise ValueError(f"EnuWarp: {n} coefficients are not 3 axes' worth")
        return monomial_degree(n // 3)

    def mono(self, Y: np.ndarray) -> np.ndarray:
        e = (Y[:, 0] - self.centre[0]) / self.half
        n = (Y[:, 1] - self.centre[1]) / self.half
        return monomials(e, n, self.degree)

    def __call__(self, Y: np.ndarray) -> np.ndarray:
        """(n, 3) displacement of ENU positions Y (n, 3)."""
        Y = np.asarray(Y, dtype=np.float64).reshape(-1, 3)
        return self.mono(Y) @ np.asarray(self.coef, np.float64).reshape(3, -1).T

    def record(self) -> dict:
        return {"centre": np.asarray(self.centre).tolist(), "half": float(self.half),
                "coef": np.asarray(self.coef).tolist()}

    @classmethod
    def from_record(cls, d: dict) -> "EnuWarp":
        return cls(np.asarray(d["centre"], np.float64), float(d["half"]), np.asarray(d["coef"], np.float64))


def undo_displacement(D, Z: np.ndarray, max_iter: int = 50, miss_m: float = 1e-6) -> np.ndarray:
    """(n, 3) points X with X + D(X) = Z, D a smooth displacement field far smaller than the
    site (a BendWarp, an EnuWarp: centimetres to metres over kilometres), by the fixed-point
    iteration X <- Z - D(X): it contracts by the warp's gradient (~1e-3), so a few steps
    reach float64 precision; it stops once a step moves no point by more than 1e-12 of the
    coordinates' scale. Far outside the site the warp's gradient grows and the iteration may
    not converge: a point whose X + D(X) misses Z by more than `miss_m` is NaN, never a wrong
    position."""
    Z = np.asarray(Z, dtype=np.float64)
    tol = 1e-12 * (1.0 + float(np.abs(Z).max(initial=0.0)))
    X = Z
    with np.errstate(over="ignore", invalid="ignore"):
        for _ in range(max_iter):
            X_new = Z - D(X)
            done = float(np.abs(X_new - X).max(initial=0.0)) <= tol
            X = X_new
            if done or not np.isfinite(X).all():
                break
        miss = np.abs(X + D(X) - Z).max(axis=-1) if len(X) else np.zeros(0)
    return np.where((np.isfinite(miss) & (miss <= miss_m))[..., None], X, np.nan)


@dataclass
class EnuMap:
    """The Euclidean upgrade of a group: affine frame -> local ENU metres,
    X -> Y + enu_warp(Y), Y = H (X + warp(X)) (warp: the metric bend step's, enu_warp: the bend
    fitted to control GCPs; each None when not applied)."""

    H: np.ndarray
    warp: BendWarp | None = None
    enu_warp: EnuWarp | None = None

    def __call__(self, X: np.ndarray) -> np.ndarray:
        X = np.asarray(X, dtype=np.float64)
        if self.warp is not None and len(X):
            X = X + self.warp(X)
        Y = apply_affine_3d(self.H, X)
        if self.enu_warp is not None and len(Y):
            Y = Y + self.enu_warp(Y)
        return Y

    def inverse(self, Y: np.ndarray) -> np.ndarray:
        """(n, 3) affine-frame points of local ENU positions Y (n, 3): the map undone step by
        step, each warp by fixed-point iteration (`undo_displacement`), H exactly. What a
        position known on the ground (a GCP's survey) is in the frame the cameras project."""
        Y = np.asarray(Y, dtype=np.float64).reshape(-1, 3)
        if self.enu_warp is not None and len(Y):
            Y = undo_displacement(self.enu_warp, Y)
        X = np.linalg.solve(self.H[:3, :3], (Y - self.H[:3, 3]).T).T
        if self.warp is not None and len(X):
            X = undo_displacement(self.warp, X)
        return X

    def same(self, other: "EnuMap") -> bool:
        """The same map (one joint reconstruction's groups share one)."""
        if not np.array_equal(self.H, other.H) or (self.warp is None) != (other.warp is None):
            return False
        if (self.enu_warp is None) != (other.enu_warp is None):
            return False
        if self.enu_warp is not None and other.enu_warp is not None \
                and self.enu_warp.record() != other.enu_warp.record():
            return False
        return self.warp is None or other.warp is None or warp_record(self.warp) == warp_record(other.warp)

    @classmethod
    def from_record(cls, rec: dict) -> "EnuMap":
        """From an upgrade record (upgrade/group_<k>.json: "H", optional "metric_warp" and
        "gcp_warp" or "dem_warp")."""
        w, g = rec.get("metric_warp"), rec.get("gcp_warp") or rec.get("dem_warp")
        return cls(np.array(rec["H"], dtype=np.float64), None if w is None else BendWarp(
            **{k: np.array(w[k], dtype=np.float64) for k in ("x0", "T", "S", "w0", "coef")}),
            None if g is None else EnuWarp.from_record(g))


def warp_record(w: BendWarp) -> dict:
    """A BendWarp as JSON lists (the record's "metric_warp")."""
    return {k: np.asarray(getattr(w, k)).tolist() for k in ("x0", "T", "S", "w0", "coef")}
