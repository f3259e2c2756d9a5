"""The Euclidean upgrade of a group as one map: affine frame -> local ENU metres,
X -> H_A (X + D(X)), D the metric bend step's warp (recon_core.euclidean.metric_bend) or none.
Shared by the upgrade stage that fits it, the files that record it and the DSM stage that
applies it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from recon_core.geometry.affine import apply_affine_3d
from recon_core.geometry.pushbroom import BendWarp


@dataclass
class EnuMap:
    """The Euclidean upgrade of a group: affine frame -> local ENU metres,
    X -> H (X + warp(X)) (warp: the metric bend step's, or None)."""

    H: np.ndarray
    warp: BendWarp | None = None

    def __call__(self, X: np.ndarray) -> np.ndarray:
        X = np.asarray(X, dtype=np.float64)
        if self.warp is not None and len(X):
            X = X + self.warp(X)
        return apply_affine_3d(self.H, X)

    def same(self, other: "EnuMap") -> bool:
        """The same map (one joint reconstruction's groups share one)."""
        if not np.array_equal(self.H, other.H) or (self.warp is None) != (other.warp is None):
            return False
        return self.warp is None or warp_record(self.warp) == warp_record(other.warp)

    @classmethod
    def from_record(cls, rec: dict) -> "EnuMap":
        """From an upgrade record (upgrade/group_<k>.json: "H", optional "metric_warp")."""
        w = rec.get("metric_warp")
        return cls(np.array(rec["H"], dtype=np.float64), None if w is None else BendWarp(
            **{k: np.array(w[k], dtype=np.float64) for k in ("x0", "T", "S", "w0", "coef")}))


def warp_record(w: BendWarp) -> dict:
    """A BendWarp as JSON lists (the record's "metric_warp")."""
    return {k: np.asarray(getattr(w, k)).tolist() for k in ("x0", "T", "S", "w0", "coef")}
