"""A group's dense affine cloud held in memory."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class DenseCloud:
    """A group's dense affine cloud."""

    xyz: np.ndarray          # (n, 3) float64, affine frame
    gray: np.ndarray         # (n,) uint8
    n_views: np.ndarray      # (n,) uint8
    reproj_px: np.ndarray    # (n,) float32
    weak: np.ndarray | None = None   # (n,) bool: two-view points of a weak (small-angle) pair,
                                     # which the DSM uses only where no other point falls

    def __len__(self) -> int:
        return len(self.xyz)
