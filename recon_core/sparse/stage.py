"""The sparse stage: per date group tiles, features, matching, tracks, incremental affine SfM;
the models are saved by recon_core.io.models."""

from __future__ import annotations

import itertools
import time

import numpy as np

from recon_core.config import Config
from recon_core.errors import ReconstructionError
from recon_core.events import EventBus, Message, StageDone
from recon_core.io.models import load_model, save_model
from recon_core.model.grouping import Group
from recon_core.model.sparse_model import SparseModel
from recon_core.model.tiling import Tile, tile_image
from recon_core.sparse.features import ImageFeatures, detect_image, detect_overview, group_tone_curves
from recon_core.sparse.matching import CoarseLink, PairMatches, coarse_link, match_pair
from recon_core.sparse.sfm import IncrementalSfM
from recon_core.sparse.tracks import build_tracks


def group_tiles(group: Group, cfg: Config) -> dict[str, list[Tile]]:
    return {im.name: tile_image(im.name, im.width, im.height, cfg.tiling.tile_size, cfg.tiling.overlap)
            for im in group.images}


def select_pairs(links: dict[tuple[int, int], CoarseLink], n_images: int, k: int) -> list[tuple[int, int]]:
    """Each image keeps its k partners with the most overview inliers (a pair kept by either side)."""
    keep = set()
    for a in range(n_images):
        mine = sorted(((l.n_inliers, p) for p, l in links.items() if a in p), reverse=True)[:k]
        keep.update(p for _, p in mine)
    return sorted(keep)


def reconstruct_group(group: Group, cfg: Config, bus: EventBus | None = None) -> tuple[SparseModel, dict]:
    """Run the sparse affine reconstruction of one date group."""
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

    t0 = time.time()
    tones, tone_warnings = group_tone_curves(group.images, cfg.features.stretch_percentiles)
    for w in tone_warnings:
        bus.message(f"group {g}: {w}", "warning", g)
    feats: list[ImageFeatures] = []
    for k, im in enumerate(group.images):
        bus.progress("features", k, len(names), im.name, group=g)
        feats.append(detect_image(im, cfg.features, tones[k]))
        if len(feats[-1]) < 100:
            bus.message(f"group {g}: {im.name}: only {len(feats[-1])} keypoints (blank, saturated or "
                        "very small image?): its tiles will hardly register", "warning", g)
    bus.progress("features", len(names), len(names), f"{sum(len(f) for f in feats)} keypoints", group=g)
    timings["features"] = time.time() - t0

    t0 = time.time()
    factor = cfg.matching.coarse_factor
    overviews = [detect_overview(im, max(1, min(factor, min(im.width, im.height) // 128)), tones[k])
                 for k, im in enumerate(group.images)]
    links: dict[tuple[int, int], CoarseLink] = {}
    for a, b in itertools.combinations(range(len(names)), 2):
        link = coarse_link(names[a], overviews[a], names[b], overviews[b])
        if link is not None:
            links[(a, b)] = link
    chosen = select_pairs(links, len(names), cfg.matching.k_partners)
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
    timings["matching"] = time.time() - t0
    if not pairs:
        raise ReconstructionError(f"group {g}: no image pair has enough verified matches "
                                  f"(>= {cfg.matching.min_inliers}); the images may not overlap "
                                  f"({', '.join(names)})")

    t0 = time.time()
    tracks = build_tracks([len(f) for f in feats], [(a, b, pm) for (a, b), pm in pairs.items()])
    all_tiles = [t for name in names for t in tiles[name]]
    sfm = IncrementalSfM(g, names, all_tiles, feats, pairs, tracks, cfg.sfm, cfg.bundle, bus, cfg.seed)
    model = sfm.run()
    timings["sfm"] = time.time() - t0
    summary = dict(model.stats)
    summary.update({"timings_s": timings, "keypoints": [len(f) for f in feats],
                    "pairs": {f"{names[a]}|{names[b]}": pm.n for (a, b), pm in pairs.items()},
                    "coarse_links": {f"{names[a]}|{names[b]}": l.n_inliers for (a, b), l in links.items()},
                    "tracks": tracks.n_tracks})
    bus.emit(StageDone("sparse", sum(timings.values()), summary, g))
    return model, summary


# -- the stage ------------------------------------------------------------------------------------
def run(state, bus: EventBus) -> dict:
    """Reconstruct every date group of the run and save its model (a group that fails is
    reported; the stage fails only when no group could be reconstructed)."""
    out = {"groups": {}}
    for g in state.groups:
        try:
            model, summary = reconstruct_group(g, state.cfg, bus)
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
