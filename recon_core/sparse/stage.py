"""The sparse stage: per date group tiles, features, matching, tracks, incremental affine SfM;
the models are saved by recon_core.io.models."""

from __future__ import annotations

import itertools
import os
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from recon_core.config import Config
from recon_core.errors import ReconstructionError
from recon_core.events import (
    BundleAdjusted,
    EventBus,
    Message,
    ModelUpdated,
    PointsAdded,
    StageDone,
    StageProgress,
    TileRegistered,
)
from recon_core.io.models import load_model, save_model
from recon_core.model.grouping import Group, tries_joint
from recon_core.model.sparse_model import Observations, SparseModel, images_per_track
from recon_core.model.tiling import Tile, tile_image
from recon_core.sparse.features import (
    ImageFeatures,
    detect_blocks,
    detect_image,
    detect_overview,
    group_tone_curves,
)
from recon_core.sparse.matching import CoarseLink, PairMatches, coarse_link, match_pair
from recon_core.sparse.refine import refine_tracks
from recon_core.sparse.sfm import IncrementalSfM
from recon_core.sparse.tracks import build_tracks

if TYPE_CHECKING:
    from recon_core.context import RunState


FEATURE_THREADS = min(4, os.cpu_count() or 1)   # images whose features are detected at once


def group_tiles(group: Group, cfg: Config) -> dict[str, list[Tile]]:
    return {im.name: tile_image(im.name, im.width, im.height, cfg.tiling.tile_size, cfg.tiling.overlap)
            for im in group.images}


def select_pairs(links: dict[tuple[int, int], CoarseLink], n_images: int, k: int,
                 groups: list[int] | None = None, k_other: int = 0) -> list[tuple[int, int]]:
    """Each image keeps its k partners with the most overview inliers (a pair kept by either side);
    with `groups` (the date group of each image), its k partners among its own group's images and
    its k_other best among the other groups' images."""
    groups = groups or [0] * n_images
    keep = set()
    for a in range(n_images):
        for same, kk in ((True, k), (False, k_other)):
            mine = sorted(((l.n_inliers, p) for p, l in links.items() if a in p
                           and (groups[p[0]] == groups[p[1]]) == same), reverse=True)[:kk]
            keep.update(p for _, p in mine)
    return sorted(keep)


def reconstruct_group(group: Group, cfg: Config, bus: EventBus | None = None,
                      image_groups: list[int] | None = None,
                      scratch_dir: Path | None = None) -> tuple[SparseModel, dict]:
    """Run the sparse affine reconstruction of one date group (or, with image_groups, the date
    group of each image, of several groups in one frame: see reconstruct_joint). The SIFT
    descriptors are spilled to a scratch folder in scratch_dir while matching reads them
    (_features_and_matches)."""
    bus = bus or EventBus()
    g = group.index
    names = [im.name for im in group.images]
    if len(names) < 2:
        raise ReconstructionError(f"group {g} has one image ({names[0]}): at least two views are "
                                  "needed to reconstruct; add an image taken within "
                                  f"{cfg.grouping.max_gap_days:g} days of it")
    timings: dict[str, float] = {}
    rng = np.random.default_rng(cfg.seed)
    tiles = group_tiles(group, cfg)

    feats, links, pairs = _features_and_matches(group, cfg, bus, tiles, rng, image_groups, timings,
                                                scratch_dir)
    t0 = time.time()
    tracks = build_tracks([len(f) for f in feats], [(a, b, pm) for (a, b), pm in pairs.items()])
    refinement = None
    if cfg.features.refine_half_px > 0:
        bus.progress("refining", 0, 1, f"{len(tracks.track)} track observations", group=g)
        t1 = time.time()
        feats, refinement = refine_tracks(group.images, feats, tracks, image_groups=image_groups,
                                          half=cfg.features.refine_half_px,
                                          min_ncc=cfg.features.refine_min_ncc, block=cfg.features.detect_block)
        timings["refine"] = time.time() - t1
        bus.progress("refining", 1, 1, f"{refinement.refined} of {refinement.candidates} tie points "
                     f"refined (median shift {refinement.median_shift_px:.2f} px)", group=g)
    all_tiles = [t for name in names for t in tiles[name]]
    sfm = IncrementalSfM(g, names, all_tiles, feats, pairs, tracks, cfg.sfm, cfg.bundle, bus, cfg.seed,
                         n_dates=len(set(image_groups)) if image_groups is not None else 1)
    if isinstance(bus, GroupRouter):
        bus.attach(sfm.m)
    model = sfm.run()
    timings["sfm"] = time.time() - t0 - timings.get("refine", 0.0)
    summary = dict(model.stats)
    summary.update({"timings_s": timings, "keypoints": [len(f) for f in feats],
                    "pairs": {f"{names[a]}|{names[b]}": pm.n for (a, b), pm in pairs.items()},
                    "coarse_links": {f"{names[a]}|{names[b]}": l.n_inliers for (a, b), l in links.items()},
                    "tracks": tracks.n_tracks})
    if refinement is not None:
        summary["tie_point_refinement"] = refinement.summary()
    bus.emit(StageDone("sparse", sum(timings.values()), summary, g))
    return model, summary


def _features_and_matches(group: Group, cfg: Config, bus: EventBus, tiles: dict[str, list[Tile]], rng,
                          image_groups: list[int] | None, timings: dict[str, float],
                          scratch_dir: Path | None) -> tuple[list[ImageFeatures], dict, dict]:
    """Each image's SIFT features, the coarse links between images and the verified matches of
    the chosen pairs. The descriptors are written to files of a scratch folder as they are
    detected (in scratch_dir: the run's OUT, swept if the run is interrupted; the system's
    temporary folder when None), memory-mapped while matching reads them, and are gone when it
    returns: the features come back without them."""
    g = group.index
    names = [im.name for im in group.images]
    with tempfile.TemporaryDirectory(prefix=".sparse_desc_", dir=scratch_dir) as folder:
        spill = Path(folder)
        t0 = time.time()
        tones, tone_warnings = group_tone_curves(group.images, cfg.features.stretch_percentiles)
        for w in tone_warnings:
            bus.message(f"group {g}: {w}", "warning", g)
        feats = _detect_group(group, cfg, bus, tones, spill)
        timings["features"] = time.time() - t0

        t0 = time.time()
        links, pairs = _match_group(group, cfg, bus, feats, tones, tiles, rng, image_groups)
        timings["matching"] = time.time() - t0
        if image_groups is not None:
            cross = np.zeros(len(names), int)
            for (a, b), pm in pairs.items():
                if image_groups[a] != image_groups[b]:
                    cross[[a, b]] += pm.n
            weak = [f"{names[k]} ({cross[k]})" for k in range(len(names)) if cross[k] < cfg.sfm.joint_min_matches]
            if weak:
                raise JointUnavailable(f"too few verified matches with the other date groups' images "
                                       f"(< {cfg.sfm.joint_min_matches}): {', '.join(weak)}")
        if not pairs:
            raise ReconstructionError(f"group {g}: no image pair has enough verified matches "
                                      f"(>= {cfg.matching.min_inliers}); the images may not overlap "
                                      f"({', '.join(names)})")

        # matching done: the refinement and the SfM need positions and intensities only
        return [f.without_descriptors() for f in feats], links, pairs


def _detect_group(group: Group, cfg: Config, bus: EventBus, tones: list, spill: Path) -> list[ImageFeatures]:
    """Each image's SIFT features (descriptors spilled to files in `spill`), the images in
    parallel threads, progress by detection block."""
    g = group.index
    names = [im.name for im in group.images]
    feats: list[ImageFeatures] = []
    # progress by detection block (a 30,000 px image is ~900 of them: minutes), and a stop
    # between blocks when the run is interrupted (the threads would finish their images)
    total = sum(detect_blocks(im, cfg.features) for im in group.images)
    blocks, lock, stop = [0], threading.Lock(), threading.Event()

    def on_block(name: str) -> None:
        if stop.is_set():
            raise KeyboardInterrupt
        with lock:
            blocks[0] += 1
            bus.progress("features", blocks[0], total, name, group=g)

    bus.progress("features", 0, total, names[0], group=g)
    # images in parallel threads (OpenCV and GDAL release the GIL): the same features in the
    # same order, in about half the time on 2 cores
    with ThreadPoolExecutor(max_workers=max(1, min(FEATURE_THREADS, len(names)))) as ex:
        detected = ex.map(lambda k: detect_image(group.images[k], cfg.features, tones[k],
                                                 spill=spill / f"{k}.desc",
                                                 on_block=lambda: on_block(names[k])), range(len(names)))
        try:
            for k, f in enumerate(detected):
                feats.append(f)
                if len(feats[-1]) < 100:
                    bus.message(f"group {g}: {names[k]}: only {len(feats[-1])} keypoints (blank, saturated "
                                "or very small image?): its tiles will hardly register", "warning", g)
        except BaseException:
            stop.set()                      # the other threads stop at their next block
            raise
    bus.progress("features", total, total, f"{sum(len(f) for f in feats)} keypoints", group=g)
    return feats


def _match_group(group: Group, cfg: Config, bus: EventBus, feats: list[ImageFeatures], tones: list,
                 tiles: dict[str, list[Tile]], rng, image_groups: list[int] | None) -> tuple[dict, dict]:
    """The coarse links between the group's images (their overviews) and the verified matches of
    the pairs chosen from them: (links, pairs)."""
    g = group.index
    names = [im.name for im in group.images]
    factor = cfg.matching.coarse_factor
    overviews = [detect_overview(im, max(1, min(factor, min(im.width, im.height) // 128)), tones[k])
                 for k, im in enumerate(group.images)]
    links: dict[tuple[int, int], CoarseLink] = {}
    for a, b in itertools.combinations(range(len(names)), 2):
        link = coarse_link(names[a], overviews[a], names[b], overviews[b])
        if link is not None:
            links[(a, b)] = link
    chosen = select_pairs(links, len(names), cfg.matching.k_partners, image_groups,
                          cfg.sfm.joint_partners if image_groups else 0)
    pairs: dict[tuple[int, int], PairMatches] = {}
    for n, (a, b) in enumerate(chosen):
        bus.progress("matching", n, len(chosen), f"{names[a]} x {names[b]}", group=g)
        pm = match_pair(feats[a], feats[b], links[(a, b)], tiles[names[a]], tiles[names[b]],
                        cfg.matching, rng)
        if pm.n >= cfg.matching.min_inliers:
            pairs[(a, b)] = pm
        else:
            bus.message(f"group {g}: {names[a]} x {names[b]}: only {pm.n} verified matches, pair dropped",
                        "warning", g)
    bus.progress("matching", len(chosen), len(chosen), f"{sum(p.n for p in pairs.values())} matches", group=g)
    return links, pairs


# -- several date groups in one frame ------------------------------------------------------------
class JointUnavailable(Exception):
    """The date groups cannot be reconstructed together (the reason is the message)."""


JOINT = -1      # the group index of a joint reconstruction while it runs


class GroupRouter(EventBus):
    """The events of a joint reconstruction, passed on as each date group's own: a tile to its
    image's group, points and models split by the groups whose images see them, progress and
    messages without a group, adjustments to every group."""

    def __init__(self, upstream: EventBus, image_group: dict[str, int]):
        super().__init__()
        self.up = upstream
        self.image_group = image_group
        self.groups = sorted(set(image_group.values()))
        self.model: SparseModel | None = None
        self._order: dict[int, dict[str, int]] = {}     # group -> tile id -> its order in the group

    def attach(self, model: SparseModel) -> None:
        """The joint model the events describe (its tiles and images do not change)."""
        self.model = model
        self._img_group = np.array([self.image_group[n] for n in model.images])
        self._tile_group = {t.id: self.image_group[t.image] for t in model.tiles}
        self._tiles_of = {g: sum(v == g for v in self._tile_group.values()) for g in self.groups}

    def _sees(self, ids: np.ndarray, model_update: bool = False) -> dict[int, np.ndarray]:
        """Per group, a mask over ids: the points observed in >= 2 of its images (its own model's,
        as split_model keeps them), one pass over the observations of these points only. New
        points, and a model update of a group that has none of its own yet, go to every group
        with an image that observes them: the initial pair is often one image of each date,
        whose points would belong to neither group until more tiles register."""
        m = self.model
        assert m is not None                     # set before any event is routed
        idx = m.active_obs()
        want = np.zeros(len(m.X), bool)
        want[ids] = True
        idx = idx[want[m.obs.track[idx]]]
        n_img = len(m.images)
        key = np.unique(m.obs.track[idx] * n_img + m.obs.img[idx])     # (track, image) pairs
        track, group = key // n_img, self._img_group[key % n_img]
        out = {}
        for g in self.groups:
            count = np.bincount(track[group == g], minlength=len(m.X))[ids]
            own = count >= 2
            out[g] = own if model_update and own.any() else count >= 1
        return out

    def emit(self, ev: object) -> None:
        if getattr(ev, "group", None) != JOINT:
            self.up.emit(ev)
        elif isinstance(ev, TileRegistered):
            g = self.image_group[ev.image]
            order = self._order.setdefault(g, {}).setdefault(ev.tile_id, len(self._order[g]))
            self.up.emit(replace(ev, group=g, order=order, total_tiles=self._tiles_of[g]))
        elif isinstance(ev, StageProgress):
            self.up.emit(replace(ev, group=None))
        elif isinstance(ev, Message):
            self.up.emit(replace(ev, group=None, text=ev.text.replace(f"group {JOINT}:", "joint reconstruction:")))
        elif isinstance(ev, BundleAdjusted):
            for k, g in enumerate(self.groups):
                self.up.emit(replace(ev, group=g, repeat=k > 0))
        elif isinstance(ev, (PointsAdded, ModelUpdated)) and self.model is not None:
            sees = self._sees(np.asarray(ev.ids, dtype=np.int64), isinstance(ev, ModelUpdated))
            for g in self.groups:
                k = sees[g]
                arrays = {f: np.asarray(getattr(ev, f))[k] for f in ("ids", "xyz", "rgb", "n_views", "reproj_px")}
                if isinstance(ev, ModelUpdated):
                    mine = {t: c for t, c in ev.cameras.items() if self._tile_group[t] == g}
                    fps = {t: f for t, f in ev.footprints.items() if t in mine}
                    self.up.emit(replace(ev, group=g, cameras=mine, footprints=fps, **arrays))
                elif k.any():
                    self.up.emit(replace(ev, group=g, **arrays))
        # StageDone of the joint run: each group's is emitted after the split


def split_model(model: SparseModel, group: int, images: list[str]) -> SparseModel:
    """The part of a joint model that belongs to one date group: its images' tiles and cameras,
    their observations, the points seen by >= 2 of its images (same frame, same track ids)."""
    keep_img = np.array([model.images.index(n) for n in images])
    img_map = np.full(len(model.images), -1)
    img_map[keep_img] = np.arange(len(keep_img))
    keep_t = np.array([t.image in images for t in model.tiles])
    t_map = np.cumsum(keep_t) - 1
    o = model.obs
    k = keep_t[o.tile]
    obs = Observations(t_map[o.tile[k]], o.track[k].copy(), o.xy[k].copy(), img_map[o.img[k]],
                       o.valid[k].copy(), o.correction[k].copy())
    mine = {t.id for t, kt in zip(model.tiles, keep_t) if kt}
    part = SparseModel(group, list(images), [t for t, kt in zip(model.tiles, keep_t) if kt],
                       model.cams[keep_t].copy(), model.registered[keep_t].copy(),
                       model.fixed[keep_t].copy(), obs, model.X.copy(), model.has_point.copy(),
                       model.gray.copy())
    idx = part.active_obs()
    part.has_point &= images_per_track(obs.track[idx], obs.img[idx], len(part.X)) >= 2
    part.register_order = [int(t_map[t]) for t in model.register_order if keep_t[t]]
    part.init_tiles = tuple(int(t_map[t]) if keep_t[t] else -1 for t in model.init_tiles)
    stats = dict(model.stats)
    joint = model.stats.get("joint") or {"images": list(model.images),
                                         "tiles_registered": int(model.registered.sum()),
                                         "tiles_total": len(model.tiles), "points": int(model.has_point.sum())}
    stats.update({"joint": joint,
                  "tiles_registered": int(part.registered.sum()), "tiles_total": len(part.tiles),
                  "points": int(part.has_point.sum()), **part.reprojection_summary(),
                  "unregistered": [t.id for t, r in zip(part.tiles, part.registered) if not r],
                  "unregistered_reasons": {t: r for t, r in model.stats.get("unregistered_reasons", {}).items()
                                           if t in mine}})
    part.stats = stats
    return part


def reconstruct_joint(groups: list[Group], cfg: Config, bus: EventBus,
                      scratch_dir: Path | None = None) -> dict[int, tuple[SparseModel, dict]] | None:
    """All date groups in one affine reconstruction (one frame), split back into one model per
    group; None (with a message) when the groups' images do not match well enough across dates
    or a group would lose its second view."""
    images = [im for g in groups for im in g.images]
    image_group = {im.name: g.index for g in groups for im in g.images}
    router = GroupRouter(bus, image_group)
    try:
        model, summary = reconstruct_group(Group(JOINT, images), cfg, router,
                                           [image_group[im.name] for im in images], scratch_dir)
    except (JointUnavailable, ReconstructionError) as exc:
        bus.message(f"date groups reconstructed one by one, not jointly: {exc}", "warning")
        return None
    out = {}
    for g in groups:
        names = [im.name for im in g.images]
        part = split_model(model, g.index, names)
        n_views = len({part.tiles[t].image for t in np.flatnonzero(part.registered)})
        if n_views < 2:
            bus.message(f"date groups reconstructed one by one, not jointly: group {g.index} keeps "
                        f"{n_views} registered image(s) in the joint reconstruction", "warning")
            return None
        s = dict(summary)
        s.update(part.stats)
        out[g.index] = (part, s)
    for g in groups:
        part, s = out[g.index]
        bus.emit(StageDone("sparse", sum(summary["timings_s"].values()), s, g.index))
    return out


# -- the stage ------------------------------------------------------------------------------------
def run(state: RunState, bus: EventBus) -> dict:
    """Reconstruct every date group of the run and save its model (a group that fails is
    reported; the stage fails only when no group could be reconstructed)."""
    out = {"groups": {}}
    joint = None
    if tries_joint(state.groups, state.cfg):
        joint = reconstruct_joint(state.groups, state.cfg, bus, state.layout.root)
    for g in state.groups:
        if joint is not None:
            model, summary = joint[g.index]
        else:
            try:
                model, summary = reconstruct_group(g, state.cfg, bus, scratch_dir=state.layout.root)
            except ReconstructionError as exc:
                bus.emit(Message("error", str(exc), g.index))
                out["groups"][str(g.index)] = {"error": str(exc), "images": [im.name for im in g.images]}
                continue
        save_model(model, state.layout)
        state.models[g.index] = model
        out["groups"][str(g.index)] = summary
    if not state.models:
        msgs = "; ".join(v["error"] for v in out["groups"].values())
        raise ReconstructionError(f"no group could be reconstructed: {msgs}")
    return out


def load(state) -> None:
    for g in state.groups:
        if state.layout.cameras(g.index).exists():
            state.models[g.index] = load_model(state.layout, g.index)
