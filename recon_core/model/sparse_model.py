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
    corr: np.ndarray | None = None   # (K, 2) the within-tile correction (px): an affine tile
    #                                  camera sees xy - corr (recon_core.bend.pushbroom)

    def __post_init__(self):
        if self.corr is None:
            self.corr = np.zeros((len(self.tile), 2))

    @property
    def correction(self) -> np.ndarray:
        """corr, which __post_init__ always makes (the same array)."""
        assert self.corr is not None
        return self.corr

    def pixels(self, idx) -> np.ndarray:
        """The pixels an affine tile camera sees, xy - corr, of observations idx."""
        return self.xy[idx] - self.correction[idx]


@dataclass
class CorrectionField:
    """A tile's within-tile correction as a quadratic in the full-image pixel (SparseModel.
    correction_field): what to subtract from a pixel before the tile's affine camera sees it."""

    centre: np.ndarray     # (2,) pixel
    half: float            # pixels per unit of the normalised coordinates
    coef: np.ndarray       # (6, 2): 1, u, v, u^2, u v, v^2 -> (col, row) correction

    def basis(self, xy: np.ndarray) -> np.ndarray:
        u, v = ((np.asarray(xy, dtype=np.float64).reshape(-1, 2) - self.centre) / self.half).T
        return np.column_stack([np.ones_like(u), u, v, u * u, u * v, v * v])

    def __call__(self, xy: np.ndarray) -> np.ndarray:
        return self.basis(xy) @ self.coef


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
    init_tiles: tuple[int, ...] = (-1, -1)
    stats: dict = field(default_factory=dict)

    # -- views of the model ---------------------------------------------------------------
    def active_obs(self) -> np.ndarray:
        """Indices of observations usable now: valid, in a registered tile, of a triangulated track."""
        o = self.obs
        return np.flatnonzero(o.valid & self.registered[o.tile] & self.has_point[o.track])

    def point_ids(self) -> np.ndarray:
        return np.flatnonzero(self.has_point)

    def views_per_image(self, min_points: int = 0, min_tiles: int = 0) -> list[tuple[int, np.ndarray]]:
        """Each image's active observations, each point once (the first observation of each
        track): [(image index, observation indices)] for the images with at least min_points
        such points in at least min_tiles tiles."""
        o, idx = self.obs, self.active_obs()
        out = []
        for i in np.unique(o.img[idx]):
            k = idx[o.img[idx] == i]
            if len(np.unique(o.tile[k])) < min_tiles:
                continue
            _, first = np.unique(o.track[k], return_index=True)
            if len(first) >= min_points:
                out.append((int(i), k[first]))
        return out

    def point_views(self, min_tiles: int = 0) -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
        """What the bend estimates read (recon_core.bend.pushbroom.estimate_bend): the point
        ids, and per image of views_per_image(min_tiles=...) (positions in those ids, pixels)."""
        o, pts = self.obs, self.point_ids()
        local = np.full(len(self.X), -1)
        local[pts] = np.arange(len(pts))
        return pts, [(local[o.track[k]], o.xy[k]) for _, k in self.views_per_image(min_tiles=min_tiles)]

    def tile_centres(self) -> np.ndarray:
        """(T, 3) the centre of each tile's active observations' points (a tile without any: the
        structure's centre), where a warp's linear part is taken for its camera (BendWarp.follow)."""
        o, idx, pts = self.obs, self.active_obs(), self.point_ids()
        cnt = np.bincount(o.tile[idx], minlength=len(self.tiles)).astype(np.float64)
        cen = np.stack([np.bincount(o.tile[idx], self.X[o.track[idx], a], minlength=len(self.tiles))
                        for a in range(3)], 1) / np.maximum(cnt, 1.0)[:, None]
        cen[cnt == 0] = self.X[pts].mean(0) if len(pts) else 0.0
        return cen

    def reprojection(self, idx: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(observation indices, pixel errors) for the active observations."""
        idx = self.active_obs() if idx is None else idx
        o = self.obs
        err = affine.reprojection_errors(self.cams, o.tile[idx], o.track[idx], o.pixels(idx), self.X)
        return idx, err

    def reprojection_summary(self) -> dict:
        """Observations in use and their mean and RMS reprojection error (px), for reports."""
        idx, err = self.reprojection()
        return {"observations": int(len(idx)),
                "mean_reproj_px": float(err.mean()) if len(err) else float("nan"),
                "rms_reproj_px": float(np.sqrt(np.mean(err ** 2))) if len(err) else float("nan")}

    def point_stats(self, ids: np.ndarray | None = None,
                    obs: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(point ids, number of distinct images, RMS reprojection px) per triangulated point:
        every one, or those of `ids` that are triangulated (from their observations only).
        `obs`: sorted active observation indices that include every active one of `ids` (a
        caller that indexes observations by track), instead of a pass over all of them."""
        idx = self.active_obs() if obs is None else obs
        n = len(self.X)
        if ids is None:
            ids = self.point_ids()
        else:
            ids = np.unique(np.asarray(ids, dtype=np.int64))
            ids = ids[self.has_point[ids]]
            want = np.zeros(n, bool)
            want[ids] = True
            idx = idx[want[self.obs.track[idx]]]
        idx, err = self.reprojection(idx)
        tr = self.obs.track[idx]
        sq = np.bincount(tr, err ** 2, minlength=n)
        cnt = np.bincount(tr, minlength=n)
        nimg = images_per_track(tr, self.obs.img[idx], n)
        return ids, nimg[ids], np.sqrt(sq[ids] / np.maximum(cnt[ids], 1))

    def tiles_at(self, image: str, cr, registered: bool = True) -> list[int]:
        """Tiles of `image` whose window contains the full-image pixel cr (registered ones only,
        unless registered is False)."""
        xy = np.asarray(cr, dtype=np.float64).reshape(1, 2)
        return [t for t, tile in enumerate(self.tiles) if tile.image == image
                and (self.registered[t] or not registered) and tile.contains(xy)[0]]

    def correction_fields(self, tiles) -> dict[int, "CorrectionField | None"]:
        """correction_field of every tile in `tiles`, from one sort of the observations."""
        o = self.obs
        k = self.active_obs()                 # the observations the correction was fitted for
        k = k[np.argsort(o.tile[k], kind="stable")]
        bounds = np.searchsorted(o.tile[k], np.arange(len(self.tiles) + 1))
        return {int(t): self.correction_field(int(t), k[bounds[t]:bounds[t + 1]]) for t in tiles}

    def correction_field(self, t: int, obs: np.ndarray | None = None) -> "CorrectionField | None":
        """The within-tile correction of tile t as a field over its pixels: a quadratic in the
        pixel fitted to the correction its observations carry (the model's departure from affine
        is quadratic inside a tile but for a small cubic and height term, ~0.01 px). None when
        they carry none. `obs`: the indices of tile t's active observations, if the caller has
        them (the others carry no correction)."""
        o = self.obs
        k = np.flatnonzero((o.tile == t) & o.valid & self.has_point[o.track]) if obs is None else obs
        if len(k) < 12 or not np.any(o.correction[k]):
            return None
        tile = self.tiles[t]
        f = CorrectionField(np.array([tile.col0 + tile.width / 2.0, tile.row0 + tile.height / 2.0]),
                            max(tile.width, tile.height) / 2.0, np.zeros((6, 2)))
        f.coef = np.linalg.lstsq(f.basis(o.xy[k]), o.correction[k], rcond=None)[0]
        return f

    def correction_at(self, t: int, xy) -> np.ndarray:
        """(n, 2) the within-tile correction of tile t at full-image pixels xy (n, 2), so that a
        pixel that is not a tie point (a GCP) is seen by the tile camera as the tie points are;
        zero where the tile has no correction."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        f = self.correction_field(t)
        return np.zeros_like(xy) if f is None else f(xy)

    def camera(self, t: int) -> AffineCamera:
        """The affine camera of tile t."""
        return AffineCamera.from_array(self.cams[t])

    def footprint(self, t: int, obs: np.ndarray | None = None) -> np.ndarray:
        """(4, 3) tile corners back-projected onto the best plane of the tile's points. `obs`:
        the indices of tile t's observations, if the caller has them."""
        o = self.obs
        if obs is None:
            return self._footprint(t, np.unique(o.track[(o.tile == t) & o.valid & self.has_point[o.track]]))
        obs = obs[o.valid[obs] & self.has_point[o.track[obs]]]
        return self._footprint(t, np.unique(o.track[obs]))

    def footprints(self, tiles) -> dict[int, np.ndarray]:
        """footprint(t) of every tile in `tiles`, from one sort of the observations (not one
        pass over all of them per tile)."""
        o = self.obs
        tracks, bounds = self.tracks_by_tile(np.flatnonzero(o.valid & self.has_point[o.track]))
        return {int(t): self._footprint(int(t), tracks[bounds[t]:bounds[t + 1]]) for t in tiles}

    def tracks_by_tile(self, obs_idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(tracks, bounds): the distinct tracks of the observations obs_idx, grouped by tile
        and sorted; tile t's are tracks[bounds[t]:bounds[t + 1]] (one sort for all tiles)."""
        o, n = self.obs, len(self.X)
        key = np.unique(o.tile[obs_idx] * n + o.track[obs_idx])
        return key % n, np.searchsorted(key // n, np.arange(len(self.tiles) + 1))

    def _footprint(self, t: int, sel: np.ndarray) -> np.ndarray:
        pts = self.X[sel] if len(sel) >= 3 else self.X[self.has_point]
        c = pts.mean(axis=0)
        _, _, vt = np.linalg.svd(pts - c, full_matrices=False)
        n = vt[-1]
        return self.camera(t).backproject_to_plane(self.tiles[t].corners(), n, n @ c)


def images_per_track(track: np.ndarray, img: np.ndarray, n: int) -> np.ndarray:
    """(n,) number of distinct images among the observations of each track."""
    n_img = int(img.max()) + 1 if len(img) else 1
    keys = track.astype(np.int64) * n_img + img
    if n * n_img <= 64_000_000:          # a count per (track, image) cell: no sort
        seen = np.bincount(keys, minlength=n * n_img).reshape(n, n_img) > 0
        return seen.sum(axis=1)
    return np.bincount(np.unique(keys) // n_img, minlength=n)


def merge_joint(models: list[SparseModel]) -> SparseModel | None:
    """The date groups' models of one joint reconstruction (the sparse stage's split, stats
    "joint") merged back into one model of all their images, in their shared frame; None unless
    every model comes from the same joint reconstruction."""
    joints = [m.stats.get("joint") for m in models]
    if len(models) < 2 or any(j is None for j in joints) or any(j != joints[0] for j in joints):
        return None
    if any(len(m.X) != len(models[0].X) for m in models):
        return None
    images, tiles, parts = [], [], []
    t_off = i_off = 0
    for m in models:
        o = m.obs
        parts.append((o.tile + t_off, o.track, o.xy, o.img + i_off, o.valid, o.corr))
        images += m.images
        tiles += m.tiles
        t_off += len(m.tiles)
        i_off += len(m.images)
    tile, track, xy, img, valid, corr = (np.concatenate(p) for p in zip(*parts))
    has = np.zeros(len(models[0].X), bool)
    X = np.zeros_like(models[0].X)
    for m in models:
        X[m.has_point] = m.X[m.has_point]
        has |= m.has_point
    merged = SparseModel(min(m.group for m in models), images, tiles,
                         np.concatenate([m.cams for m in models]),
                         np.concatenate([m.registered for m in models]),
                         np.concatenate([m.fixed for m in models]),
                         Observations(tile, track, xy.reshape(-1, 2), img, valid, corr.reshape(-1, 2)), X, has,
                         models[0].gray.copy(), stats={"joint": joints[0]})
    idx = merged.active_obs()
    merged.has_point &= images_per_track(merged.obs.track[idx], merged.obs.img[idx], len(X)) >= 2
    return merged
