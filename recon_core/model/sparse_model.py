"""The affine model of one date group: tile cameras, observations and points.

Written by the sparse stage, read by every later stage and by the viewer (its files:
recon_core.io.models).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from recon_core.geometry import affine
from recon_core.geometry.camera import AffineCamera
from recon_core.model.tiling import Tile


@dataclass
class Observations:
    """Every (tile, track) observation: a feature seen by every tile of its image that contains it."""

    tile: np.ndarray       # (K,) tile index
    track: np.ndarray      # (K,) track index
    xy: np.ndarray         # (K, 2) full-image pixels
    img: np.ndarray        # (K,) image index
    valid: np.ndarray      # (K,) bool: False once rejected as an outlier


@dataclass
class SparseModel:
    """The affine reconstruction of one group."""

    group: int
    images: list[str]
    tiles: list[Tile]
    cams: np.ndarray                  # (T, 2, 4)
    registered: np.ndarray            # (T,) bool
    fixed: np.ndarray                 # (T, 2, 4) bool: gauge-fixed camera entries
    obs: Observations
    X: np.ndarray                     # (N, 3) one slot per track
    has_point: np.ndarray             # (N,) bool
    gray: np.ndarray                  # (N,) uint8 track intensity
    register_order: list[int] = field(default_factory=list)
    init_tiles: tuple[int, int] = (-1, -1)
    stats: dict = field(default_factory=dict)

    # -- views of the model ---------------------------------------------------------------
    def active_obs(self) -> np.ndarray:
        """Indices of observations usable now: valid, in a registered tile, of a triangulated track."""
        o = self.obs
        return np.flatnonzero(o.valid & self.registered[o.tile] & self.has_point[o.track])

    def point_ids(self) -> np.ndarray:
        return np.flatnonzero(self.has_point)

    def reprojection(self, idx: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(observation indices, pixel errors) for the active observations."""
        idx = self.active_obs() if idx is None else idx
        o = self.obs
        err = affine.reprojection_errors(self.cams, o.tile[idx], o.track[idx], o.xy[idx], self.X)
        return idx, err

    def point_stats(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(point ids, number of distinct images, RMS reprojection px) per triangulated point."""
        idx, err = self.reprojection()
        tr = self.obs.track[idx]
        n = len(self.X)
        sq = np.bincount(tr, err ** 2, minlength=n)
        cnt = np.bincount(tr, minlength=n)
        nimg = images_per_track(tr, self.obs.img[idx], n)
        ids = self.point_ids()
        return ids, nimg[ids], np.sqrt(sq[ids] / np.maximum(cnt[ids], 1))

    def tiles_at(self, image: str, cr, registered: bool = True) -> list[int]:
        """Tiles of `image` whose window contains the full-image pixel cr (registered ones only,
        unless registered is False)."""
        xy = np.asarray(cr, dtype=np.float64).reshape(1, 2)
        return [t for t, tile in enumerate(self.tiles) if tile.image == image
                and (self.registered[t] or not registered) and tile.contains(xy)[0]]

    def camera(self, t: int) -> AffineCamera:
        """The affine camera of tile t."""
        return AffineCamera.from_array(self.cams[t])

    def footprint(self, t: int) -> np.ndarray:
        """(4, 3) tile corners back-projected onto the best plane of the tile's points."""
        o = self.obs
        sel = np.unique(o.track[(o.tile == t) & o.valid & self.has_point[o.track]])
        pts = self.X[sel] if len(sel) >= 3 else self.X[self.has_point]
        c = pts.mean(axis=0)
        _, _, vt = np.linalg.svd(pts - c, full_matrices=False)
        n = vt[-1]
        return self.camera(t).backproject_to_plane(self.tiles[t].corners(), n, n @ c)


def images_per_track(track: np.ndarray, img: np.ndarray, n: int) -> np.ndarray:
    """(n,) number of distinct images among the observations of each track."""
    n_img = int(img.max()) + 1 if len(img) else 1
    keys = np.unique(track.astype(np.int64) * n_img + img)
    return np.bincount(keys // n_img, minlength=n)
