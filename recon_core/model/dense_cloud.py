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

    def __len__(self) -> int:
        return len(self.xyz)
