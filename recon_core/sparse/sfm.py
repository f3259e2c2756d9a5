"""Incremental affine structure from motion over the tiles of one date group.

One affine camera (2 x 4) per tile, one global affine structure per group, no RPC, no GCP.

Order of work (the paper's, with its guards: parallax checks, the exact 12-dof gauge):
1. initial image pair = the pair with the sparsest verified matching among pairs that show
   parallax (sigma3/sigma4 of the centred measurement matrix); initial tile pair inside it =
   the tile pair with the most matches that itself shows parallax;
2. Tomasi-Kanade factorisation initialises the two tile cameras and the points; the canonical
   affine frame fixes exactly the 12 gauge dof;
3. tiles of the initial images are registered nearest first, then the others by their number
   of 2D-3D correspondences; each tile camera by RANSAC resection; new tracks triangulated;
4. local bundle adjustment after each registration, global whenever the model grew by a set
   fraction, and at the end.
"""

from __future__ import annotations

import time

import numpy as np

from recon_core.bend.closing import (ImageModelCheck, StraightLines, bend_step, check_image_models,
                                      closing_plan, image_ties, straight_lines, within_tile)
from recon_core.config import BundleConfig, SfmConfig
from recon_core.errors import ReconstructionError
from recon_core.events import BundleAdjusted, EventBus, ModelUpdated, PointsAdded, TileRegistered
from recon_core.geometry import affine
from recon_core.model.sparse_model import Observations, SparseModel, images_per_track
from recon_core.model.tiling import Tile
from recon_core.sparse.bundle import bundle_adjust
from recon_core.sparse.features import ImageFeatures
from recon_core.sparse.matching import PairMatches
from recon_core.sparse.tracks import Tracks


def point_conditioning(cams: np.ndarray, obs_cam: np.ndarray, obs_pt: np.ndarray, n: int,
                       ids: np.ndarray | None = None) -> np.ndarray:
    """(n,) sqrt(lambda_min / lambda_max) of sum M^T M over each point's observations (or, with
    `ids`, (len(ids),) for those points only, from their observations only).

    The affine counterpart of a triangulation angle: for two orthographic views it is
    sin(angle / 2), about B/H / 2 (0 for identical views); repeated views do not change it. The
    affine frame distorts it, and not by one global factor: differently for baselines in
    different directions (on `large`, a pair of true B/H 0.23 scores above one of B/H 0.49;
    docs: research-notes.md, "The affine frame cannot rank pairs by angle"). So it is compared with the model's own best points
    (90th percentile), never with an absolute threshold, and it catches near-identical views,
    not the weaker of two reasonable pairs; not with the median either, which a weak pair's
    many matches can own.
    """
    if ids is not None:
        ids = np.asarray(ids, dtype=np.int64)
        slot = np.full(n, -1, np.int64)
        slot[ids] = np.arange(len(ids))
        k = slot[obs_pt] >= 0
        obs_cam, obs_pt, n = obs_cam[k], slot[obs_pt[k]], len(ids)
    G = np.einsum("tri,trj->tij", cams[:, :, :3], cams[:, :, :3]).reshape(-1, 9)   # per camera
    A = np.zeros((n, 9))
    for c in range(9):
        A[:, c] = np.bincount(obs_pt, G[obs_cam, c], minlength=n)
    ev = np.linalg.eigvalsh(A.reshape(n, 3, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.sqrt(np.clip(ev[:, 0], 0, None) / ev[:, 2])
    return np.nan_to_num(out, nan=0.0)


def build_observations(tiles: list[Tile], image_names: list[str], feats: list[ImageFeatures],
                       tracks: Tracks) -> Observations:
    """Expand track nodes to one observation per tile containing the feature."""
    tiles_of = {k: [t for t, tl in enumerate(tiles) if tl.image == name] for k, name in enumerate(image_names)}
    parts = []
    for k in range(len(image_names)):
        nodes = np.flatnonzero(tracks.img == k)
        xy = feats[k].xy[tracks.feat[nodes]]
        for t in tiles_of[k]:
            inside = tiles[t].contains(xy)
            sel = nodes[inside]
            parts.append((np.full(len(sel), t), tracks.track[sel], xy[inside], np.full(len(sel), k)))
    tile, track, xy, img = (np.concatenate(p) for p in zip(*parts))
    return Observations(tile.astype(np.int64), track.astype(np.int64), xy.reshape(-1, 2),
                        img.astype(np.int64), np.ones(len(tile), bool))


# a tile with fewer 2D-3D correspondences than sfm.resect_min_inliers (a corner of the images'
# overlap) is registered from its image's camera as a prior when at least this many of them
# agree with it: 8 unknowns, 2 conditions per point, and the prior (docs: method.md)
MIN_WITH_PRIOR = 6
# ... and the prior weighs a hundredth of the points in what they fix (the 2D part), while it
# still sets what a flat set of points cannot (the response to height)
FEW_PRIOR_WEIGHT = 0.1


class IncrementalSfM:
    """Runs the incremental reconstruction of one group and emits events as it grows."""

    def __init__(self, group: int, image_names: list[str], tiles: list[Tile], feats: list[ImageFeatures],
                 pairs: dict[tuple[int, int], PairMatches], tracks: Tracks, cfg: SfmConfig,
                 ba_cfg: BundleConfig, bus: EventBus | None = None, seed: int = 0, n_dates: int = 1):
        """n_dates: how many date groups the images come from (a joint reconstruction: > 1)."""
        self.cfg, self.ba_cfg = cfg, ba_cfg
        self.n_dates = n_dates
        self.bus = bus or EventBus()
        self.rng = np.random.default_rng(seed)
        self.pairs = pairs
        self.tile_index = {t.id: k for k, t in enumerate(tiles)}
        obs = build_observations(tiles, image_names, feats, tracks)
        gray = np.zeros(tracks.n_tracks)
        cnt = np.zeros(tracks.n_tracks)
        for k, f in enumerate(feats):
            nodes = np.flatnonzero(tracks.img == k)
            np.add.at(gray, tracks.track[nodes], f.gray[tracks.feat[nodes]])
            np.add.at(cnt, tracks.track[nodes], 1)
        T = len(tiles)
        self.m = SparseModel(group, image_names, tiles, np.zeros((T, 2, 4)), np.zeros(T, bool),
                             np.zeros((T, 2, 4), bool), obs, np.zeros((tracks.n_tracks, 3)),
                             np.zeros(tracks.n_tracks, bool),
                             (gray / np.maximum(cnt, 1)).astype(np.uint8))
        self._ba_at = 0
        self._sent_points = np.zeros(tracks.n_tracks, bool)
        # tracks to triangulate: after a tile registers, only those it sees (a new view); after
        # a global adjustment (cameras moved, outliers dropped), every pending track again
        o = self.m.obs
        self._by_track = np.argsort(o.track, kind="stable")        # observations of each track
        self._track_start = np.searchsorted(o.track[self._by_track], np.arange(tracks.n_tracks + 1))
        self._by_tile = np.argsort(o.tile, kind="stable")          # ... and of each tile
        self._tile_start = np.searchsorted(o.tile[self._by_tile], np.arange(T + 1))
        self._pending = np.zeros(tracks.n_tracks, bool)
        self._retry_all = True
        self._cond_ref: float | None = None    # the model's 90th-percentile conditioning at its
        #                                         last outlier filter (before each global adjustment)
        self._regularised = {"toward_a_tile_of_its_image": 0, "toward_its_image_camera": 0}
        self._few_points: dict[str, int] = {}    # tile id -> correspondences it was registered from
        self._counts: np.ndarray | None = None     # _counts_now's
        self._correction_info: dict = {}
        self._images = ImageModelCheck()          # which images their model explains (closing)
        self._straight = StraightLines(False, "off (sfm.bend_step = false)")

    # -- initial pair -------------------------------------------------------------------------
    def choose_initial_pair(self) -> tuple[int, int, dict]:
        """Initial tile pair (tile indices) by the paper's rule guarded by a parallax test."""
        by_pair = []
        n_min, par_min = self.cfg.init_min_inliers, self.cfg.init_min_parallax
        for (a, b), pm in self.pairs.items():
            good = [s for s in pm.tile_pairs if s.n_inliers >= n_min and s.parallax >= par_min]
            if good:
                by_pair.append((pm.n, (a, b), good))
        if not by_pair:
            best = max((s.parallax for pm in self.pairs.values() for s in pm.tile_pairs), default=0.0)
            raise ReconstructionError(
                f"group {self.m.group}: no image pair has a tile pair with >= {n_min} verified matches "
                f"and parallax (sigma3/sigma4 >= {par_min}; best seen {best:.2f}): the views may not "
                "overlap, or the baseline is too small to reconstruct 3D")
        by_pair.sort(key=lambda e: e[0])          # sparsest matching first = widest angle
        n, (a, b), good = by_pair[0]
        tp = max(good, key=lambda s: s.n_inliers)
        info = {"image_pair": [self.m.images[a], self.m.images[b]], "pair_matches": n,
                "tile_pair": [tp.tile_i, tp.tile_j], "tile_pair_inliers": tp.n_inliers,
                "parallax_ratio": tp.parallax,
                "candidates": [{"pair": [self.m.images[p[0]], self.m.images[p[1]]], "matches": c}
                               for c, p, _ in by_pair]}
        return self.tile_index[tp.tile_i], self.tile_index[tp.tile_j], info

    def initialise(self) -> dict:
        ta, tb, info = self.choose_initial_pair()
        m, o = self.m, self.m.obs
        in_a = o.valid & (o.tile == ta)
        in_b = o.valid & (o.tile == tb)
        common = np.intersect1d(o.track[in_a], o.track[in_b])
        xa = _obs_xy(o, in_a, common)
        xb = _obs_xy(o, in_b, common)
        W = np.stack([xa, xb])
        cams, X, _ = affine.tomasi_kanade(W)
        cams, X, _ = affine.canonical_gauge(cams, X)
        m.cams[ta], m.cams[tb] = cams[0], cams[1]
        m.registered[[ta, tb]] = True
        m.fixed[ta] = True
        row = int(np.argmax(np.abs(cams[1][:, 2])))
        m.fixed[tb, row] = True
        m.init_tiles = (ta, tb)
        m.register_order += [ta, tb]
        m.X[common] = X
        m.has_point[common] = True
        self._triangulate_new()
        self._filter_outliers()
        # the pair's structure is shown at once (the first adjustment follows, and the viewer
        # takes its result as a model update)
        for k, t in enumerate((ta, tb)):
            self._emit_tile(t, int(np.sum(o.tile[m.active_obs()] == t)), order=k)
        self._emit_points()
        self._bundle("global")
        info["init_points"] = int(m.has_point.sum())
        return info

    # -- registration ---------------------------------------------------------------------------
    def run(self) -> SparseModel:
        t0 = time.time()
        m = self.m
        init = self.initialise()
        ta, tb = m.init_tiles
        init_imgs = {m.tiles[ta].image, m.tiles[tb].image}
        phase1 = [t for t in range(len(m.tiles)) if m.tiles[t].image in init_imgs and not m.registered[t]]
        ref = {m.tiles[ta].image: m.tiles[ta].centre, m.tiles[tb].image: m.tiles[tb].centre}
        phase1.sort(key=lambda t: np.linalg.norm(m.tiles[t].centre - ref[m.tiles[t].image]))
        why: dict[int, str] = {}        # tile -> why its last attempt failed
        # each tile's state at its last attempt: its correspondences and the registered tiles
        # of its image (-1: never tried)
        tried = np.full((2, len(m.tiles)), -1, np.int64)
        img_of = np.array([m.images.index(tl.image) for tl in m.tiles], np.int64)
        for t in phase1:
            self._attempt(t, why, tried, self._counts_now(), self._registered_per_image(img_of)[img_of])
        # then by number of 2D-3D correspondences; a tile that failed is tried again once it
        # has more correspondences, or once more tiles of its image are registered
        tried_few = np.full_like(tried, -1)   # the same, for attempts from the image's camera
        while True:
            counts = self._counts_now()
            img_reg = self._registered_per_image(img_of)[img_of]
            cand = np.flatnonzero(~m.registered & ((counts > tried[0]) | (img_reg > tried[1]))
                                  & (counts >= self.cfg.resect_min_inliers))
            if len(cand):
                best = int(cand[np.argmax(counts[cand])])
                self._attempt(best, why, tried, counts, img_reg)
                continue
            # no tile has enough correspondences for a resection of its own: the one with the
            # most is registered from its image's camera (and its points may lift others)
            cand = np.flatnonzero(~m.registered & ((counts > tried_few[0]) | (img_reg > tried_few[1]))
                                  & (counts >= MIN_WITH_PRIOR))
            if not len(cand):
                break
            best = int(cand[np.argmax(counts[cand])])
            self._attempt(best, why, tried_few, counts, img_reg, few=True)
        bend = self._close()
        self._emit_model()
        counts = self._correspondence_counts()
        reasons = {}
        for t in np.flatnonzero(~m.registered):
            reasons[m.tiles[t].id] = self._unregistered_reason(int(t), why.get(int(t)), int(counts[t]))
            self.bus.message(f"group {m.group}: tile {m.tiles[t].id} not registered: "
                             f"{reasons[m.tiles[t].id]}", "warning", m.group)
        m.stats = {"init": init, "tiles_registered": int(m.registered.sum()), "tiles_total": len(m.tiles),
                   "points": int(m.has_point.sum()), **m.reprojection_summary(),
                   "unregistered": [m.tiles[t].id for t in np.flatnonzero(~m.registered)],
                   "unregistered_reasons": reasons,
                   "flat_tiles_regularised": dict(self._regularised),
                   "few_point_tiles": dict(self._few_points),
                   "within_tile_correction": {"images": [m.images[i] for i in self._correction_info.get("images", [])],
                                              "rms_px": self._correction_info.get("rms_px", 0.0),
                                              "max_px": self._correction_info.get("max_px", 0.0)},
                   "image_models": self._images.summary(),
                   "bend_step": {**self._straight.summary(), "steps": bend},
                   "seconds": time.time() - t0}
        return m

    def _close(self) -> list[dict]:
        """The closing adjustments (recon_core.bend.closing.closing_plan): the per-image ties, then
        rounds with the within-tile correction refitted to the tied structure, each started by the
        bend step where the sensors are straight line arrays. Only with views of several dates:
        one pass's views (2-3, scanned alike) leave the vertical warps invisible, and the
        corrections would only move the structure along them (docs: "What the views can see").
        The tie and the correction stand aside for an image its model does not explain. Returns
        the bend steps' summaries."""
        m = self.m
        rounds = self.cfg.correction_rounds if self.n_dates > 1 else 0
        self._images = check_image_models(m)
        if self._images.warning():
            self.bus.message(f"group {m.group}: {self._images.warning()}", "warning", m.group)
        if self.cfg.bend_step and rounds > 0:
            self._straight = straight_lines(m)
            if not self._straight.straight:
                self.bus.message(f"group {m.group}: the bend step stands aside: {self._straight.why}",
                                 "info", m.group)
        elif self.cfg.bend_step:
            self._straight = StraightLines(False, "one date, or no correction round")
        bend: list[dict] = []
        for step in closing_plan(rounds, self._straight.straight):
            if step.name == "filter":
                self._filter_outliers()
            elif step.name == "bend":
                bend.append(bend_step(m))
                if bend[-1]["applied"]:
                    self.bus.message(f"group {m.group}: bend step: {bend[-1]['warps_seen']} of 9 quadratic "
                                     f"warps seen, the structure unbent by {bend[-1]['warp_rms_px']:.2f} px RMS",
                                     "info", m.group)
            else:
                self._bundle("global", final=True, correct=step.correct, converge=step.converge)
        return bend

    def _correspondence_counts(self) -> np.ndarray:
        """(T,) number of 2D-3D correspondences of every tile (one pass over the observations)."""
        o = self.m.obs
        return np.bincount(o.tile[o.valid & self.m.has_point[o.track]], minlength=len(self.m.tiles))

    def _counts_now(self) -> np.ndarray:
        """_correspondence_counts, kept up to date between global events: a registration
        changes it by the observations it refuses and the points it adds (`_count_delta`); an
        outlier filter, which may touch any of them, makes it count again."""
        if self._counts is None:
            self._counts = self._correspondence_counts()
        return self._counts

    def _count_delta(self, obs: np.ndarray, sign: int) -> None:
        """Observations `obs` became (+1) or stopped being (-1) correspondences."""
        if self._counts is not None and len(obs):
            self._counts += sign * np.bincount(self.m.obs.tile[obs], minlength=len(self.m.tiles))

    # Observations by track and by tile: the work after each registration follows the tile
    # and its neighbourhood, not every observation of the model (which grows as the site).
    # Each helper returns indices sorted as in the observation arrays, so what is computed from
    # them is what a mask over all of them gave, in the same order.
    def _obs_of_tracks(self, tracks: np.ndarray) -> np.ndarray:
        return _gather(self._by_track, self._track_start, tracks)

    def _obs_of_tiles(self, tiles: np.ndarray) -> np.ndarray:
        return _gather(self._by_tile, self._tile_start, tiles)

    def _active(self, idx: np.ndarray) -> np.ndarray:
        """The active ones among observation indices idx (SparseModel.active_obs)."""
        m, o = self.m, self.m.obs
        return idx[o.valid[idx] & m.registered[o.tile[idx]] & m.has_point[o.track[idx]]]

    def _attempt(self, t: int, why: dict[int, str], tried: np.ndarray, counts: np.ndarray,
                 img_reg: np.ndarray, few: bool = False) -> None:
        """Try to register t (`few`: from fewer correspondences than a resection of its own
        needs, with its image's camera as a prior); remember the state it was tried in (its
        correspondences, the registered tiles of its image: tried[:, t]) and, if it failed, why."""
        tried[:, t] = counts[t], img_reg[t]
        reason = self._register(t, few)
        if reason is None:
            why.pop(t, None)
        else:
            why[t] = reason

    def _registered_per_image(self, img_of: np.ndarray) -> np.ndarray:
        """Registered tiles per image (img_of: each tile's image index)."""
        return np.bincount(img_of[self.m.registered], minlength=len(self.m.images))

    def _register(self, t: int, few: bool = False) -> str | None:
        """Register tile t; None when done, else why it could not be (it may be retried).
        `few`: with fewer correspondences than sfm.resect_min_inliers, from its image's camera."""
        m, o = self.m, self.m.obs
        in_t = self._obs_of_tiles(np.array([t]))
        sel = in_t[o.valid[in_t] & m.has_point[o.track[in_t]]]
        X, x = m.X[o.track[sel]], o.pixels(sel)
        if len(sel) < self.cfg.resect_min_inliers:
            if not few:
                return f"{len(sel)} 2D-3D correspondences (< {self.cfg.resect_min_inliers})"
            got = self._resect_few(t, X, x)
            if isinstance(got, str):
                return f"{len(sel)} 2D-3D correspondences (< {self.cfg.resect_min_inliers}): {got}"
            P, inl = got
            self._few_points[m.tiles[t].id] = int(inl.sum())
            return self._add_tile(t, P, inl, sel, in_t)
        try:
            P, inl = affine.resect_ransac(X, x, thresh_px=self.cfg.resect_thresh_px,
                                          iters=self.cfg.resect_ransac_iters,
                                          rng=self.rng, min_inliers=self.cfg.resect_min_inliers)
        except ReconstructionError as exc:
            return f"no consistent camera among its {len(sel)} correspondences ({exc})"
        cond = affine.points_conditioning(X[inl])
        if cond < self.cfg.min_points_conditioning:
            # nearly coplanar points fix 6 of the 8 parameters: the response to height comes
            # from the image's other tiles, or from all of the image's correspondences
            prior, how = self._image_prior(t)
            if prior is None:
                return (f"its points are nearly coplanar (conditioning {cond:.4f} < "
                        f"{self.cfg.min_points_conditioning}) and its image has no registered tile "
                        "and too flat a set of correspondences to lean on yet")
            P = _resect_regularised(X[inl], x[inl], prior, weight=1.0)
            self._regularised[how] += 1
        return self._add_tile(t, P, inl, sel, in_t)

    def _resect_few(self, t: int, X: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray] | str:
        """A camera for tile t from too few correspondences for a resection of its own: pulled
        toward its image's camera (the nearest registered tile of its image, else one camera
        fitted to all the image's correspondences), from the correspondences that agree with the
        result within sfm.resect_thresh_px (at least MIN_WITH_PRIOR of them). The closing
        adjustments then hold it in its image's pushbroom model with the others. Returns
        (P, inliers), or why not."""
        if len(X) < MIN_WITH_PRIOR:
            return "too little overlap with the registered tiles, or too little texture"
        prior, _ = self._image_prior(t)
        if prior is None:
            return "no registered tile of its image and no camera of the whole image to lean on yet"
        P, inl = resect_with_prior(X, x, prior, self.cfg.resect_thresh_px, MIN_WITH_PRIOR)
        if P is None:
            return (f"fewer than {MIN_WITH_PRIOR} of them agree with its image's camera within "
                    f"{self.cfg.resect_thresh_px} px")
        return P, inl

    def _add_tile(self, t: int, P: np.ndarray, inl: np.ndarray, sel: np.ndarray, in_t: np.ndarray) -> None:
        """Tile t registered with camera P (inl: which of its correspondences sel it agrees
        with): its new points, a local adjustment, a global one when the model has grown enough."""
        m, o = self.m, self.m.obs
        m.cams[t] = P
        m.registered[t] = True
        self._pending[o.track[in_t]] = True
        m.register_order.append(t)
        o.valid[sel[~inl]] = False
        self._count_delta(sel[~inl], -1)
        self._triangulate_new()
        self._bundle("local", around=t)
        n_reg = int(m.registered.sum())
        if n_reg >= max((1.0 + self.cfg.global_ba_growth) * self._ba_at, self._ba_at + 4):
            self._filter_outliers()
            self._bundle("global")
        self._emit_tile(t, int(inl.sum()), obs=in_t)
        self._emit_points()
        return None

    def _image_prior(self, t: int) -> tuple[np.ndarray | None, str]:
        """The camera tile t leans on: the nearest registered tile of its image, else one camera
        of its whole image (None when neither exists yet), and which it is."""
        prior = self._neighbour_camera(t)
        if prior is not None:
            return prior, "toward_a_tile_of_its_image"
        return self._image_camera(self.m.tiles[t].image), "toward_its_image_camera"

    def _neighbour_camera(self, t: int) -> np.ndarray | None:
        m = self.m
        same = [k for k in range(len(m.tiles)) if m.registered[k] and m.tiles[k].image == m.tiles[t].image]
        if not same:
            return None
        k = min(same, key=lambda k: np.linalg.norm(m.tiles[k].centre - m.tiles[t].centre))
        return m.cams[k]

    def _image_camera(self, image: str) -> np.ndarray | None:
        """One affine camera fitted (robustly) to every 2D-3D correspondence of an image, over
        all its tiles: a prior for a flat tile when no tile of its image is registered yet.
        None when those points are themselves too flat or too few."""
        m, o = self.m, self.m.obs
        k = m.images.index(image)
        sel = np.flatnonzero((o.img == k) & o.valid & m.has_point[o.track])
        _, first = np.unique(o.track[sel], return_index=True)    # a feature once, not per tile
        sel = sel[first]
        if len(sel) < 3 * self.cfg.resect_min_inliers:
            return None
        X, x = m.X[o.track[sel]], o.pixels(sel)
        try:
            # the whole image departs from one affine camera by a few pixels (pushbroom)
            thresh = self.cfg.image_camera_thresh_factor * self.cfg.resect_thresh_px
            P, inl = affine.resect_ransac(X, x, thresh_px=thresh, iters=self.cfg.resect_ransac_iters,
                                          rng=self.rng, min_inliers=3 * self.cfg.resect_min_inliers)
        except ReconstructionError:
            return None
        # The relative conditioning of a whole image's points falls with its width; what
        # matters is how well they fix the camera's response to height: the pixel error its
        # uncertainty causes over the model's height range must stay under a pixel.
        Xi = X[inl]
        Xc = Xi - Xi.mean(axis=0)
        _, sv, vt = np.linalg.svd(Xc, full_matrices=False)
        normal = vt[-1]
        ids = m.point_ids()
        h = (m.X[ids] - Xi.mean(axis=0)) @ normal
        span = float(np.subtract(*np.percentile(h, [98, 2])))
        sigma = max(0.3, float(np.sqrt(np.mean(np.sum((affine.project(P, Xi) - x[inl]) ** 2, axis=1) / 2))))
        if span * sigma / max(sv[-1], 1e-12) > 1.0:
            return None
        return P

    # -- points ------------------------------------------------------------------------------
    def _triangulate_new(self) -> None:
        """Triangulate tracks seen in >= 2 distinct images among registered tiles: the tracks
        of the tiles registered since the last call, or all of them after a global adjustment."""
        m, o = self.m, self.m.obs
        if self._retry_all:
            use = np.flatnonzero(o.valid & m.registered[o.tile] & ~m.has_point[o.track])
        else:
            use = self._obs_of_tracks(np.flatnonzero(self._pending & ~m.has_point))
            use = use[o.valid[use] & m.registered[o.tile[use]]]
        self._pending[:] = False
        self._retry_all = False
        if len(use) == 0:
            return
        # the candidate tracks numbered 0..n-1: the work follows them, not the whole model
        cand, slot = np.unique(o.track[use], return_inverse=True)
        nimg = images_per_track(slot, o.img[use], len(cand))
        keep = nimg[slot] >= 2
        use, slot = use[keep], slot[keep]
        if len(use) == 0:
            return
        X, ok = affine.triangulate_tracks(m.cams, o.tile[use], slot, o.pixels(use), len(cand))
        made = np.zeros(len(cand), bool)
        made[slot] = True
        made &= ok
        new = cand[made]
        m.X[new] = X[made]
        m.has_point[new] = True
        # reject new points whose reprojection is poor
        sel = use[made[slot]]
        err = affine.reprojection_errors(m.cams, o.tile[sel], o.track[sel], o.pixels(sel), m.X)
        bad = np.unique(o.track[sel][err > self.cfg.max_reproj_px])
        m.has_point[bad] = False
        # new points from views too close in angle never enter (rather than appearing and
        # being dropped at the next global adjustment)
        if self.cfg.min_triangulation_ratio > 0:
            new = new[m.has_point[new]]
            ref = self._cond_ref
            if ref is None:           # before the first outlier filter: the initial pair's points
                old = m.has_point.copy()
                old[new] = False
                old = np.flatnonzero(old)
                if len(old) < 50:
                    old = m.point_ids()
                ref = np.percentile(self._conditioning(old), 90) if len(old) else None
            if ref is not None:
                cond = self._conditioning(new)
                m.has_point[new[cond < self.cfg.min_triangulation_ratio * ref]] = False
        added = self._obs_of_tracks(new[m.has_point[new]])
        self._count_delta(added[o.valid[added]], +1)

    def _conditioning(self, ids: np.ndarray | None = None) -> np.ndarray:
        """point_conditioning over the active observations: of every track, or of `ids`
        (distinct track ids: from their own observations)."""
        m, o = self.m, self.m.obs
        idx = m.active_obs() if ids is None else self._active(self._obs_of_tracks(ids))
        return point_conditioning(m.cams, o.tile[idx], o.track[idx], len(m.X), ids)

    def _filter_outliers(self) -> None:
        """Invalidate observations with large error; drop points left with < 2 images, and
        points triangulated from views too close in angle (`SfmConfig.min_triangulation_ratio`)."""
        m, o = self.m, self.m.obs
        self._counts = None
        idx, err = m.reprojection()
        o.valid[idx[err > self.cfg.max_reproj_px]] = False
        idx = m.active_obs()
        nimg = images_per_track(o.track[idx], o.img[idx], len(m.X))
        m.has_point &= nimg >= 2
        if self.cfg.min_triangulation_ratio > 0:
            cond = self._conditioning()
            ids = m.point_ids()
            if len(ids):
                ref = np.percentile(cond[ids], 90)
                m.has_point[ids] &= cond[ids] >= self.cfg.min_triangulation_ratio * ref
                self._cond_ref = float(ref)

    # -- tiles left unregistered ---------------------------------------------------------------
    def _unregistered_reason(self, t: int, last_try: str | None, count: int) -> str:
        """What the report says of a tile left unregistered: its last try's reason, or, when
        that is a count of correspondences alone (or it was never tried), why so few."""
        few = f"2D-3D correspondences (< {self.cfg.resect_min_inliers})"
        if last_try is None or last_try.endswith(few):
            return f"{count} {few}: " + self._why_few(t)
        return last_try

    def _why_few(self, t: int) -> str:
        """Why an unregistered tile has too few 2D-3D correspondences: its tracks that registered
        tiles of other images see have no 3D point (a pair of views too close in angle:
        sfm.min_triangulation_ratio), or there are too few such tracks at all."""
        m, o = self.m, self.m.obs
        own = o.tile == t
        if not own.any():
            return "no feature of it is matched in another image: no overlap, or too little texture"
        mine = np.unique(o.track[own & o.valid])
        k = np.flatnonzero(np.isin(o.track, mine) & o.valid & m.registered[o.tile] & (o.img != o.img[own][0]))
        shared = np.unique(o.track[k])
        lost = int(np.sum(~m.has_point[shared]))
        if lost >= self.cfg.resect_min_inliers:
            return (f"{lost} of its tracks are seen by registered tiles of other images but have no 3D point "
                    "(dropped: views too close in angle, sfm.min_triangulation_ratio, or a poor reprojection)")
        return "too little overlap with the registered tiles, or too little texture"

    # -- bundle adjustment --------------------------------------------------------------------
    def _bundle(self, scope: str, around: int | None = None, final: bool = False,
                correct: bool = False, converge: bool | None = None) -> None:
        """A local adjustment around tile `around` or a global one; `final`: a closing global
        adjustment, with the per-image ties; `correct`: the within-tile correction refitted
        first; `converge`: to BundleConfig.rel_tol (default: when final; the others stop at
        growing_rel_tol)."""
        converge = final if converge is None else converge
        m, o = self.m, self.m.obs
        if scope == "global":
            idx = m.active_obs()
            if len(idx) == 0:
                return
            if correct:
                self._correction_info = within_tile(m, idx, self._images.unexplained)
            free_cams, free_pts = np.flatnonzero(m.registered), m.point_ids()
            self._ba_at = int(m.registered.sum())
            self._retry_all = True          # cameras moved, outliers dropped: every track again
        else:
            # the tiles sharing the most points with `around`, from the observations of its
            # tracks only; then the observations of the free points: every one the adjustment
            # uses (an observation in a free tile is of a free point), in the same order
            assert around is not None                # a local adjustment is around a tile
            tr = np.unique(o.track[self._active(self._obs_of_tiles(np.array([around])))])
            shared = np.bincount(o.tile[self._active(self._obs_of_tracks(tr))], minlength=len(m.tiles))
            shared[around] = 0
            nb = np.argsort(-shared)[: self.cfg.local_ba_window]
            free_cams = np.unique(np.concatenate([[around], nb[shared[nb] > 0]]))
            free_pts = np.unique(o.track[self._active(self._obs_of_tiles(free_cams))])
            idx = self._active(self._obs_of_tracks(free_pts))
            if len(idx) == 0:
                return
        res = bundle_adjust(m.cams, m.X, o.tile[idx], o.track[idx], o.pixels(idx), free_cams, free_pts,
                            m.fixed, loss=self.ba_cfg.loss, f_scale=self.ba_cfg.loss_scale_px,
                            max_nfev=self.ba_cfg.max_nfev if scope == "global" else self.ba_cfg.local_max_nfev,
                            rel_tol=self.ba_cfg.rel_tol if converge else self.ba_cfg.growing_rel_tol,
                            ties=image_ties(m, idx, self.cfg.tie_sigma_px, self._images.unexplained)
                            if final else None, solver=self.ba_cfg.solver)
        m.cams, m.X = res.cams, res.X
        self.bus.emit(BundleAdjusted(m.group, scope, res.cost_before, res.cost_after, res.rms_px,
                                     len(free_cams), len(free_pts), res.seconds))
        if scope == "global":
            self._emit_model()

    # -- events ------------------------------------------------------------------------------
    def _emit_tile(self, t: int, n_inliers: int, order: int | None = None, obs: np.ndarray | None = None) -> None:
        m = self.m
        order = m.register_order.index(t) if order is None else order
        self.bus.emit(TileRegistered(m.group, m.tiles[t].id, m.tiles[t].image, m.cams[t].copy(),
                                     m.footprint(t, obs), n_inliers, order, len(m.tiles)))

    def _emit_points(self) -> None:
        m = self.m
        new = m.has_point & ~self._sent_points
        if not new.any():
            return
        ids = np.flatnonzero(new)
        ids, nimg, rms = m.point_stats(ids, obs=self._active(self._obs_of_tracks(ids)))
        g = m.gray[ids]
        self.bus.emit(PointsAdded(m.group, ids.copy(), m.X[ids].copy(), np.stack([g, g, g], 1),
                                  nimg, rms))
        self._sent_points |= new

    def _emit_model(self) -> None:
        m = self.m
        ids, nimg, rms = m.point_stats()
        g = m.gray[ids]
        reg = np.flatnonzero(m.registered)
        self.bus.emit(ModelUpdated(m.group, {m.tiles[t].id: m.cams[t].copy() for t in reg},
                                   {m.tiles[t].id: f for t, f in m.footprints(reg).items()}, ids.copy(),
                                   m.X[ids].copy(), np.stack([g, g, g], 1), nimg, rms))
        self._sent_points = m.has_point.copy()


def _gather(by: np.ndarray, start: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """Sorted indices of the entries of `keys` in a grouping (by: indices sorted by key, start:
    where each key's run begins)."""
    keys = np.asarray(keys, dtype=np.int64)
    a, b = start[keys], start[keys + 1]
    n = b - a
    return np.sort(by[np.repeat(a - np.cumsum(n) + n, n) + np.arange(n.sum())])


def _obs_xy(o: Observations, mask: np.ndarray, tracks: np.ndarray) -> np.ndarray:
    """Pixel of each track in `tracks` among the observations selected by mask (first one)."""
    idx = np.flatnonzero(mask)
    order = np.argsort(o.track[idx], kind="stable")
    tr_sorted = o.track[idx][order]
    pos = np.searchsorted(tr_sorted, tracks)
    return o.pixels(idx)[order][pos]


def resect_with_prior(X: np.ndarray, x: np.ndarray, prior: np.ndarray, thresh_px: float,
                      min_inliers: int) -> tuple[np.ndarray | None, np.ndarray]:
    """A camera from few 2D-3D correspondences (X (k, 3), x (k, 2)) pulled toward a prior
    camera (2, 4): fitted to all, then to those within thresh_px of the fit, until the set no
    longer changes (at most 5 times). Returns (P, inliers), or (None, inliers) when fewer than
    min_inliers agree."""
    inl = np.ones(len(X), bool)
    Xh = np.hstack([X, np.ones((len(X), 1))])
    for _ in range(5):
        if inl.sum() < min_inliers:
            return None, inl
        P = _resect_regularised(X[inl], x[inl], prior, weight=FEW_PRIOR_WEIGHT)
        new = np.linalg.norm(Xh @ P.T - x, axis=1) < thresh_px
        if (new == inl).all():
            return P, inl
        inl = new
    if inl.sum() < min_inliers:
        return None, inl
    return _resect_regularised(X[inl], x[inl], prior, weight=FEW_PRIOR_WEIGHT), inl


def _resect_regularised(X: np.ndarray, x: np.ndarray, prior: np.ndarray, weight: float) -> np.ndarray:
    """Resection pulled toward a prior camera (for nearly planar point sets)."""
    n = len(X)
    Xh = np.hstack([X, np.ones((n, 1))])
    scale = np.sqrt(np.mean(np.sum((X - X.mean(0)) ** 2, axis=1)))
    reg = weight * np.sqrt(n) * np.diag([scale, scale, scale, 1.0])
    P = np.zeros((2, 4))
    for r in range(2):
        A = np.vstack([Xh, reg])
        b = np.concatenate([x[:, r], reg @ prior[r]])
        P[r] = np.linalg.lstsq(A, b, rcond=None)[0]
    return P
