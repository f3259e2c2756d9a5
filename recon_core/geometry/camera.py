"""The affine camera of a tile: x = M X + t, a full-image pixel (col, row) of a 3D point X.

The parameters are one (2, 4) array P = [M | t] (the site format's pixel convention: the centre of
the top-left pixel is (0, 0)). Stacks of tile cameras stay (n, 2, 4) arrays for the vectorised
algebra (recon_core.geometry.affine) and the bundle adjustment; everything else that needs one
camera's projection, linear part or a window-relative version goes through `AffineCamera`, so a
camera model with more structure (e.g. one per image) has one place to plug in.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class AffineCamera:
    """One 8-parameter affine camera x = M X + t."""

    P: np.ndarray                     # (2, 4) [M | t]

    def __post_init__(self) -> None:
        P = np.array(self.P, dtype=np.float64).reshape(2, 4)
        P.setflags(write=False)
        object.__setattr__(self, "P", P)

    @classmethod
    def from_array(cls, P) -> "AffineCamera":
        return cls(np.asarray(P, dtype=np.float64))

    def to_array(self) -> np.ndarray:
        """A writable (2, 4) copy of the parameters."""
        return self.P.copy()

    @property
    def linear(self) -> np.ndarray:
        """M (2, 3): pixels per unit of the 3D frame (the camera's Jacobian)."""
        return self.P[:, :3]

    @property
    def offset(self) -> np.ndarray:
        """t (2,): the pixel of the frame's origin."""
        return self.P[:, 3]

    def project(self, X) -> np.ndarray:
        """(n, 3) points -> (n, 2) full-image pixels."""
        X = np.asarray(X, dtype=np.float64).reshape(-1, 3)
        return X @ self.linear.T + self.offset

    def in_window(self, col0: float, row0: float) -> "AffineCamera":
        """The same camera with pixels counted from a window's origin (col0, row0)."""
        P = self.to_array()
        P[:, 3] -= (col0, row0)
        return AffineCamera(P)

    def backproject_to_plane(self, uv, normal, d: float) -> np.ndarray:
        """(k, 2) pixels -> (k, 3) points on the plane normal . X = d (least squares)."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        A = np.vstack([self.linear, np.asarray(normal, dtype=np.float64).reshape(1, 3)])
        b = np.column_stack([uv - self.offset, np.full(len(uv), float(d))])
        return np.linalg.lstsq(A, b.T, rcond=None)[0].T
