"""The sparse stage for one date group: tiles, features, matching, tracks, incremental SfM.

Also reads and writes the affine model of a group:
  affine/group_<k>/cameras.json     tiles (offset, size), registration flag and 2 x 4 camera
  affine/group_<k>/sparse.ply       points (affine frame, float64), grey colour, views, error
  affine/group_<k>/observations.npz every (tile, track) observation: tile, track, xy, img, valid;
                                    point_ids = track id of each sparse.ply vertex, in order
"""

from __future__ import annotations

import itertools
import json
import time
from pathlib import Path

import numpy as np

from .config import Config
from .errors import ReconstructionError
from .events import EventBus, StageDone
from .features import ImageFeatures, detect_image, detect_overview, tone_curve_for
from .grouping import Group
from .io_utils import atomic_path, write_json
from .matching import CoarseLink, PairMatches, coarse_link, match_pair
from .sfm import IncrementalSfM, Observations, SparseModel
from .tiling import Tile, tile_image
from .tracks import build_tracks


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
    tone = tone_curve_for(group.images, cfg.features.stretch_percentiles)
    feats: list[ImageFeatures] = []
    for k, im in enumerate(group.images):
        bus.progress("features", k, len(names), im.name, group=g)
        feats.append(detect_image(im, cfg.features, tone))
    bus.progress("features", len(names), len(names), f"{sum(len(f) for f in feats)} keypoints", group=g)
    timings["features"] = time.time() - t0

    t0 = time.time()
    factor = cfg.matching.coarse_factor
    overviews = [detect_overview(im, max(1, min(factor, min(im.width, im.height) // 128)), tone)
                 for im in group.images]
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


# -- persistence --------------------------------------------------------------------------------

def group_dir(out: Path, g: int) -> Path:
    return Path(out) / "affine" / f"group_{g}"


def save_model(model: SparseModel, out: Path) -> Path:
    from .dsm import write_ply

    d = group_dir(out, model.group)
    d.mkdir(parents=True, exist_ok=True)
    doc = {"group": model.group, "images": model.images,
           "frame": "affine; gauge = canonical frame of the initial tile pair "
                    "(first camera [I2|0|0], one row of the second camera [0 0 1|0])",
           "camera_convention": "x = P @ [X, Y, Z, 1]: full-image pixel (col, row), centre of the "
                                "top-left pixel at (0, 0)",
           "init_tiles": [model.tiles[t].id for t in model.init_tiles],
           "register_order": [model.tiles[t].id for t in model.register_order],
           "tiles": [dict(t.to_dict(), registered=bool(model.registered[k]),
                          camera=model.cams[k].tolist(), fixed=model.fixed[k].tolist())
                     for k, t in enumerate(model.tiles)],
           "stats": model.stats}
    write_json(d / "cameras.json", doc)
    ids, nimg, rms = model.point_stats()
    g = model.gray[ids]
    write_ply(d / "sparse.ply", model.X[ids], np.stack([g, g, g], 1),
              {"n_views": nimg.astype(np.float32),
               "reproj_px": rms.astype(np.float32)})
    o = model.obs
    with atomic_path(d / "observations.npz") as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, tile=o.tile, track=o.track, xy=o.xy, img=o.img, valid=o.valid,
                                gray=model.gray, point_ids=ids)
    return d


def load_model(out: Path, g: int) -> SparseModel:
    from .dsm import read_ply

    d = group_dir(out, g)
    doc = json.loads((d / "cameras.json").read_text())
    tiles = [Tile(t["image"], t["ti"], t["tj"], t["col0"], t["row0"], t["width"], t["height"])
             for t in doc["tiles"]]
    cams = np.array([t["camera"] for t in doc["tiles"]], dtype=np.float64).reshape(-1, 2, 4)
    fixed = np.array([t["fixed"] for t in doc["tiles"]], dtype=bool).reshape(-1, 2, 4)
    reg = np.array([t["registered"] for t in doc["tiles"]], dtype=bool)
    z = np.load(d / "observations.npz")
    obs = Observations(z["tile"], z["track"], z["xy"], z["img"], z["valid"])
    gray = z["gray"]
    xyz, _, _ = read_ply(d / "sparse.ply")
    ids = z["point_ids"].astype(np.int64)
    X = np.zeros((len(gray), 3))
    X[ids] = xyz
    has = np.zeros(len(gray), bool)
    has[ids] = True
    index = {t.id: k for k, t in enumerate(tiles)}
    m = SparseModel(doc["group"], doc["images"], tiles, cams, reg, fixed, obs, X, has, gray,
                    [index[i] for i in doc["register_order"]],
                    tuple(index[i] for i in doc["init_tiles"]), doc.get("stats", {}))
    return m
