"""Tiles of d x d pixels whose neighbours overlap by d/3, small enough for an affine camera."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Window:
    """A window of one image in full-image pixels: columns col0 .. col0 + width - 1, rows
    row0 .. row0 + height - 1 (docs: site-format.md; the centre of the top-left pixel is (0, 0))."""

    image: str
    col0: int
    row0: int
    width: int
    height: int

    @property
    def centre(self) -> np.ndarray:
        return np.array([self.col0 + (self.width - 1) / 2.0, self.row0 + (self.height - 1) / 2.0])

    def contains(self, xy, margin: float = 0.0) -> np.ndarray:
        """(n, 2) full-image (col, row) -> (n,) bool: inside the window (shrunk by margin)."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        return ((xy[:, 0] >= self.col0 - 0.5 + margin) & (xy[:, 0] <= self.col0 + self.width - 0.5 - margin)
                & (xy[:, 1] >= self.row0 - 0.5 + margin) & (xy[:, 1] <= self.row0 + self.height - 0.5 - margin))

    def corners(self) -> np.ndarray:
        """(4, 2) full-image pixel corners, clockwise from top-left."""
        c0, r0 = self.col0 - 0.5, self.row0 - 0.5
        c1, r1 = c0 + self.width, r0 + self.height
        return np.array([[c0, r0], [c1, r0], [c1, r1], [c0, r1]])

    def pixel(self, fx: float, fy: float) -> tuple[float, float]:
        """Fractions of the window (0 = left/top edge, 1 = right/bottom edge) -> full-image
        (col, row)."""
        return self.col0 - 0.5 + fx * self.width, self.row0 - 0.5 + fy * self.height

    def fraction(self, col: float, row: float) -> tuple[float, float]:
        """Inverse of `pixel`."""
        return (col - self.col0 + 0.5) / self.width, (row - self.row0 + 0.5) / self.height


@dataclass(frozen=True)
class Tile(Window):
    """A tile: a window of one image at grid position (ti, tj) of its image's tiling."""

    ti: int = 0      # tile row index
    tj: int = 0      # tile column index

    @property
    def id(self) -> str:
        return f"{self.image}:{self.ti}_{self.tj}"

    def to_dict(self) -> dict:
        return {"id": self.id, "image": self.image, "ti": self.ti, "tj": self.tj,
                "col0": self.col0, "row0": self.row0, "width": self.width, "height": self.height}

    @classmethod
    def from_dict(cls, d: dict) -> "Tile":
        return cls(d["image"], d["col0"], d["row0"], d["width"], d["height"], ti=d["ti"], tj=d["tj"])


def tile_layout(length: int, d: int, overlap: int, slack: float = 0.1) -> tuple[list[int], int]:
    """Start offsets and tile length along one axis.

    Tiles are d long and overlap by at least `overlap`; the last one ends at the border. To avoid
    near-duplicate tiles (a 1024 px image cut at d = 1000 into two tiles shifted by 24 px), tiles
    may stretch by up to `slack` * d, and starts are spread evenly.
    """
    if d <= overlap:
        raise ValueError(f"overlap {overlap} must be smaller than the tile size {d}")
    d_max = int(round(d * (1.0 + slack)))
    if length <= d_max:
        return [0], length
    n = int(np.ceil((length - overlap) / (d_max - overlap)))
    size = min(length, max(d, int(np.ceil((length + (n - 1) * overlap) / n))))
    starts = np.round(np.linspace(0, length - size, n)).astype(int)
    return sorted(set(starts.tolist())), size


def tile_image(name: str, width: int, height: int, d: int = 1000, overlap: int | None = None,
               slack: float = 0.1) -> list[Tile]:
    """Cut an image into tiles of about d x d (clipped to the image when it is smaller)."""
    overlap = d // 3 if overlap is None else overlap
    rows, h = tile_layout(height, d, overlap, slack)
    cols, w = tile_layout(width, d, overlap, slack)
    return [Tile(name, c0, r0, w, h, ti=ti, tj=tj) for ti, r0 in enumerate(rows) for tj, c0 in enumerate(cols)]
