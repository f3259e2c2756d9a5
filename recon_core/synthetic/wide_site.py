"""A render-free wide site: the bend of tile-camera bundle adjustment, measured in seconds.

The full pipeline needs an hour on `large` to show how the affine structure bends. The bend does
not come from the images' content: it comes from the pushbroom's departure from affine inside
each tile and from what the tile cameras leave free. So it can be measured without rendering:
points on the true scene surface, projected by the true pushbroom cameras (plus Gaussian pixel
noise), observed in every tile of every image that contains them (d x d tiles overlapping by
d/3, as the pipeline cuts them), adjusted from the truth itself (the bundle adjustment then finds
the bend on its own), and compared with the truth after one best-fit 3D affine map.

Truth for tests and benchmarks only; nothing here is read by the pipeline.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from recon_core.geometry.geodesy import LocalFrame
from recon_core.model.tiling import Tile, tile_image
from recon_core.sparse.bundle import BAResult, bundle_adjust
from recon_core.synthetic.truth import bend_report

if TYPE_CHECKING:
    from recon_core.synthetic.generator import SynthPreset


@dataclass
class WideSite:
    names: list[str]
    tiles: list[Tile]
    tile_image: np.ndarray        # (T,) image index of each tile
    X_true: np.ndarray            # (N, 3) local ENU metres (the scene's local frame)
    obs_cam: np.ndarray           # (K,) tile index
    obs_pt: np.ndarray            # (K,) point index
    obs_xy: np.ndarray            # (K, 2) full-image pixels (col, row), noisy
    height_px_per_m: np.ndarray   # (I, 2) pixel shift per metre of height (col, row), per image

    def best_tile_cameras(self, X: np.ndarray) -> np.ndarray:
        """(T, 2, 4) least-squares affine camera of each tile for points X."""
        P = np.zeros((len(self.tiles), 2, 4))
        for t in range(len(self.tiles)):
            k = self.obs_cam == t
            A = np.hstack([X[self.obs_pt[k]], np.ones((int(k.sum()), 1))])
            P[t] = np.linalg.lstsq(A, self.obs_xy[k], rcond=None)[0].T
        return P

    def views_per_image(self, max_per_image: int | None = None, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
        """Each point once per image, as the SfM passes a model's views on (SparseModel.
        views_per_image): [(point indices, pixels (k, 2))] per image, at most max_per_image
        points per image (drawn at random with `seed`)."""
        rng = np.random.default_rng(seed)
        img = self.tile_image[self.obs_cam]
        out = []
        for i in range(len(self.names)):
            k = np.flatnonzero(img == i)
            _, first = np.unique(self.obs_pt[k], return_index=True)
            k = k[first]
            if max_per_image is not None and len(k) > max_per_image:
                k = np.sort(rng.choice(k, max_per_image, replace=False))
            out.append((self.obs_pt[k], self.obs_xy[k]))
        return out

    def gauge(self) -> np.ndarray:
        """Held camera entries: tile 0 whole and one row of tile 1 (12 numbers, as the SfM)."""
        fixed = np.zeros((len(self.tiles), 2, 4), bool)
        fixed[0] = True
        fixed[1, 0] = True
        return fixed

    def adjust(self, cams: np.ndarray, X: np.ndarray, *, ties=None, max_nfev: int = 300) -> BAResult:
        """Global bundle adjustment of every tile camera and point."""
        return bundle_adjust(cams, X, self.obs_cam, self.obs_pt, self.obs_xy, np.arange(len(cams)),
                             np.arange(len(X)), self.gauge(), max_nfev=max_nfev, ties=ties)


    def grow(self, *, correction: bool, r0_m: float = 600.0, step_m: float = 300.0,
             max_nfev: int = 100, log=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """An incremental reconstruction in rings, as the SfM grows its model: the tiles within
        r0_m of the site's centre (ground position of their points) adjusted from the truth of
        their points, then rings of step_m: new tiles resected on the current points, new
        points triangulated with the current cameras, a global adjustment of all. With
        `correction`, the within-tile correction (recon_core.bend.image_model) is refitted
        from the current structure before every adjustment after the first, as the SfM does:
        nothing of the truth but the first patch enters. Returns (cams, X, point_in_model).
        `log`: called with a line per ring (radius, tiles, points, the adjustment's time)."""
        from recon_core.bend.pushbroom import tile_corrections
        from recon_core.geometry import affine

        T, N = len(self.tiles), len(self.X_true)
        cnt = np.bincount(self.obs_cam, minlength=T)
        centre = np.zeros((T, 2))
        for a in range(2):
            centre[:, a] = np.bincount(self.obs_cam, self.X_true[self.obs_pt, a], minlength=T) / np.maximum(cnt, 1)
        dist = np.linalg.norm(centre - np.median(self.X_true[:, :2], axis=0), axis=1)
        dist[cnt < 20] = np.inf
        last = float(dist[np.isfinite(dist)].max())
        radii = list(np.arange(r0_m, last, step_m)) + [last]
        cams = np.zeros((T, 2, 4))
        X = np.zeros((N, 3))
        corr = np.zeros_like(self.obs_xy)
        tile_on = np.zeros(T, bool)
        point_on = np.zeros(N, bool)
        img_of_obs = self.tile_image[self.obs_cam]
        fixed = None
        stage = -1
        while radii:
            stage += 1
            radius = radii.pop(0)
            new_tiles = (dist <= radius) & ~tile_on
            if stage > 0:
                new_tiles = self._resect(new_tiles, tile_on, cams, X, point_on, corr)
                if not radii and new_tiles.any() and (np.isfinite(dist) & ~tile_on & ~new_tiles).any():
                    radii.append(radius)    # the last ring again while it registers tiles: a tile
                                            # waits for enough points (as the SfM retries it)
            tile_on |= new_tiles
            seen = tile_on[self.obs_cam]
            n_img = np.zeros(N, int)
            pairs = np.unique(np.stack([self.obs_pt[seen], img_of_obs[seen]], 1), axis=0)
            np.add.at(n_img, pairs[:, 0], 1)
            new_pts = (n_img >= 2) & ~point_on
            if stage == 0:
                X[new_pts] = self.X_true[new_pts]
                point_on |= new_pts
                cams = np.where(tile_on[:, None, None], self.best_tile_cameras(self.X_true), 0.0)
                first = np.flatnonzero(tile_on)
                other = next(t for t in first if self.tile_image[t] != self.tile_image[first[0]])
                fixed = np.zeros((T, 2, 4), bool)
                fixed[first[0]] = True
                fixed[other, 0] = True
            else:
                k = np.flatnonzero(seen & new_pts[self.obs_pt])
                ids, slot = np.unique(self.obs_pt[k], return_inverse=True)
                Xn, ok = affine.triangulate_tracks(cams, self.obs_cam[k], slot.ravel(),
                                                   self.obs_xy[k] - corr[k], len(ids))
                X[ids[ok]] = Xn[ok]
                point_on[ids[ok]] = True
            use = np.flatnonzero(seen & point_on[self.obs_pt])
            if correction and stage > 0:
                corr[:] = 0.0
                corr[use] = tile_corrections(X[self.obs_pt[use]], self.obs_xy[use], self.obs_cam[use],
                                             img_of_obs[use])[0]
            res = bundle_adjust(cams, X, self.obs_cam[use], self.obs_pt[use], self.obs_xy[use] - corr[use],
                                np.flatnonzero(tile_on), np.flatnonzero(point_on), fixed, max_nfev=max_nfev)
            cams, X = res.cams, res.X
            if log is not None:
                log(f"ring {stage} ({radius:.0f} m): {int(tile_on.sum())} of {T} tiles, "
                    f"{int(point_on.sum())} points, adjustment {res.iterations} it, {res.seconds:.1f} s, "
                    f"{res.rms_px:.3f} px")
        return cams, X, point_on

    def _resect(self, cand: np.ndarray, tile_on: np.ndarray, cams: np.ndarray, X: np.ndarray,
                point_on: np.ndarray, corr: np.ndarray, min_points: int = 30) -> np.ndarray:
        """Resect the candidate tiles on the current points, as the SfM registers a tile (a
        nearly flat set of points regularised toward the nearest tile of its image); returns the
        tiles resected (the others wait for a later ring)."""
        from recon_core.geometry import affine
        from recon_core.sparse.sfm import _resect_regularised

        done = np.zeros_like(cand)
        for t in np.flatnonzero(cand):
            k = np.flatnonzero((self.obs_cam == t) & point_on[self.obs_pt])
            if len(k) < min_points:
                continue
            Xt, xt = X[self.obs_pt[k]], self.obs_xy[k] - corr[k]
            Xh = np.hstack([Xt, np.ones((len(k), 1))])
            P = np.linalg.lstsq(Xh, xt, rcond=None)[0].T
            if affine.points_conditioning(Xt) < 0.01:
                same = np.flatnonzero(tile_on & (self.tile_image == self.tile_image[t]))
                if not len(same):
                    continue
                near = same[np.argmin([np.hypot(self.tiles[s].col0 - self.tiles[t].col0,
                                                self.tiles[s].row0 - self.tiles[t].row0) for s in same])]
                P = _resect_regularised(Xt, xt, cams[near], weight=1.0)
            cams[t] = P
            done[t] = True
        return done


def observe_in_tiles(names: list[str], cams: list, views: list[tuple[np.ndarray, np.ndarray]], d: int,
                     min_obs: int = 20):
    """Each image's observations (point indices, pixels (k, 2)) in every d x d tile of the image
    (cut as the pipeline cuts it, cams[i].width x height) that contains them; tiles with fewer
    than min_obs are left out. Returns (tiles, tile image (T,), tile of each observation, point,
    pixel)."""
    tiles, tile_img, oc, op, ox = [], [], [], [], []
    for i, (n, cam, (p, uv)) in enumerate(zip(names, cams, views)):
        for t in tile_image(n, cam.width, cam.height, d):
            k = np.flatnonzero((uv[:, 0] >= t.col0) & (uv[:, 0] <= t.col0 + t.width - 1)
                               & (uv[:, 1] >= t.row0) & (uv[:, 1] <= t.row0 + t.height - 1))
            if len(k) < min_obs:
                continue
            tiles.append(t)
            tile_img.append(i)
            oc.append(np.full(len(k), len(tiles) - 1))
            op.append(p[k])
            ox.append(uv[k])
    return tiles, np.array(tile_img), np.concatenate(oc), np.concatenate(op), np.concatenate(ox)


def make_wide_site(preset: str | SynthPreset = "flat", seed: int = 0, *, images: list[str] | None = None,
                   n_points: int = 30000, noise_px: float = 0.1, d: int = 1000,
                   rng_seed: int = 1, min_obs_per_tile: int = 20) -> WideSite:
    """Points over the common footprint of the preset's images (or of `images`), seen by >= 2
    images. Uses the preset's cameras without rendering (design_cameras); `preset` is a name or
    a SynthPreset (e.g. a preset with larger images: a wide site that is never rendered)."""
    from recon_core.synthetic.generator import design_cameras

    scene, cams = design_cameras(preset, seed)
    if images:
        cams = {k: v for k, v in cams.items() if k in images}
    names = sorted(cams)
    frame = LocalFrame(scene.lon0, scene.lat0, scene.h0)
    rng = np.random.default_rng(rng_seed)
    boxes = []
    for n in names:
        xy = scene.llh_to_local(cams[n].footprint(scene.h0))[:, :2]
        boxes.append((xy[:, 0].min(), xy[:, 0].max(), xy[:, 1].min(), xy[:, 1].max()))
    b = np.array(boxes)
    x = rng.uniform(b[:, 0].max(), b[:, 1].min(), n_points)
    y = rng.uniform(b[:, 2].max(), b[:, 3].min(), n_points)
    llh = scene.local_to_llh(np.stack([x, y, scene.height(x, y)], -1))
    X = frame.geodetic_to_enu(llh)
    up = frame.enu_to_geodetic(X + [0.0, 0.0, 1.0])

    views, dz = [], []
    for n in names:
        cam = cams[n]
        uv_exact = cam.project(llh)
        dz.append(np.median(cam.project(up[:200]) - uv_exact[:200], axis=0))
        views.append((np.arange(n_points), uv_exact + rng.normal(0.0, noise_px, uv_exact.shape)))
    tiles, tile_img, oc, op, ox = observe_in_tiles(names, [cams[n] for n in names], views, d,
                                                   min_obs_per_tile)
    n_img = np.zeros(n_points, int)
    for i in range(len(names)):
        n_img[np.unique(op[tile_img[oc] == i])] += 1
    keep = n_img >= 2
    remap = np.cumsum(keep) - 1
    m = keep[op]
    return WideSite(names, tiles, tile_img, X[keep], oc[m], remap[op[m]], ox[m], np.array(dz))


def structure_vs_truth(X: np.ndarray, X_true: np.ndarray) -> dict:
    """One best-fit 3D affine map from X to the truth; residual RMS (3D, per axis) and how much
    of the vertical residual a quadratic surface explains (bend_report)."""
    A = np.hstack([X, np.ones((len(X), 1))])
    r = A @ np.linalg.lstsq(A, X_true, rcond=None)[0] - X_true
    out = {"rms_m": float(np.sqrt((r ** 2).sum(1).mean())),
           "rms_enu_m": np.sqrt((r ** 2).mean(0)).tolist()}
    out.update(bend_report(X_true, r[:, 2]))
    return out


def observability(site: WideSite, X: np.ndarray | None = None, max_per_image: int = 20000,
                  seed: int = 0, altitude_m: float | None = None) -> dict:
    """recon_core.bend.pushbroom.warp_observability of the site's images over the points X
    (default: the truth, a metric frame), each point once per image (at most max_per_image per
    image); with `altitude_m`, each image's 1D perspective fixed by physics (physical_depth)
    instead of free."""
    from recon_core.bend.pushbroom import physical_depth, warp_observability

    X = site.X_true if X is None else X
    images = site.views_per_image(max_per_image, seed)
    depth = None
    if altitude_m is not None:
        depth = []
        for pts, xy in images:
            Xh = np.hstack([X[pts], np.ones((len(pts), 1))])
            depth.append(physical_depth(np.linalg.lstsq(Xh, xy, rcond=None)[0].T, altitude_m))
    return warp_observability(X, images, fixed_depth=depth)


def image_ties(site: WideSite, cams: np.ndarray, X: np.ndarray, weight: float,
               max_samples: int = 48, seed: int = 0) -> list:
    """One image-model tie per image (recon_core.bend.image_model), sampled on each tile's
    points."""
    from recon_core.bend.image_model import image_tie

    rng = np.random.default_rng(seed)
    ties = []
    for i in range(len(site.names)):
        tids = np.flatnonzero(site.tile_image == i)
        samples = []
        for t in tids:
            k = site.obs_pt[site.obs_cam == t]
            if len(k) > max_samples:
                k = rng.choice(k, max_samples, replace=False)
            samples.append(X[k])
        ties.append(image_tie(cams[tids], samples, tids, weight))
    return ties
