"""Registration on flat ground: a tile whose points are nearly coplanar is never dropped for
good. A synthetic group of three affine views of mostly flat ground with one area of relief:
the first tile tried in the third image is flat (most correspondences) and no tile of that
image is registered yet."""

from __future__ import annotations

import itertools

import numpy as np

from recon_core.config import BundleConfig, MatchingConfig, SfmConfig
from recon_core.events import EventBus, Message
from recon_core.model.tiling import tile_image
from recon_core.sparse.features import ImageFeatures
from recon_core.sparse.matching import PairMatches, verify_by_tile_pairs
from recon_core.sparse.sfm import IncrementalSfM
from recon_core.sparse.tracks import build_tracks

SIZE, D, OVERLAP = 1000, 600, 200
DIRS = [(0.0, 0.0), (0.35, 0.05), (-0.10, 0.30)]          # height -> pixel shift per view


def _scene(rng, extra_image: bool = False):
    flat = np.column_stack([np.vstack([rng.uniform(0, SIZE, (3000, 2)), rng.uniform(0, 400, (1500, 2))]),
                            rng.normal(0, 0.05, 4500)])          # a dense flat corner: tried first
    relief = np.column_stack([rng.uniform(650, SIZE, (700, 2)), rng.uniform(0, 40, 700)])
    X = np.vstack([flat, relief])
    dirs = DIRS + ([(0.2, -0.2)] if extra_image else [])
    names = [f"v{k}.tif" for k in range(len(dirs))]
    feats, vis = [], []
    for k, (a, b) in enumerate(dirs):
        P = np.array([[1.0, 0.02 * k, a, 5.0 * k], [-0.01 * k, 1.0, b, -3.0 * k]])
        if extra_image and k == 3:
            P[:, 3] += 2000.0                                   # sees none of the scene
        x = X @ P[:, :3].T + P[:, 3] + rng.normal(0, 0.1, (len(X), 2))
        v = np.flatnonzero(np.all((x > 0) & (x < SIZE - 1), axis=1))
        if extra_image and k == 3:
            v = np.arange(50)
            x[v] = rng.uniform(0, SIZE - 1, (50, 2))
        vis.append(v)
        n = len(v)
        feats.append(ImageFeatures(names[k], x[v], rng.integers(0, 255, (n, 128)).astype(np.uint8),
                                   np.ones(n, np.float32), np.ones(n, np.float32),
                                   np.full(n, 128, np.uint8)))
    tiles = {nm: tile_image(nm, SIZE, SIZE, D, OVERLAP) for nm in names}
    pairs, rng2 = {}, np.random.default_rng(1)
    for a, b in itertools.combinations(range(len(names)), 2):
        common = np.intersect1d(vis[a], vis[b])
        ia, ib = np.searchsorted(vis[a], common), np.searchsorted(vis[b], common)
        tps = list(itertools.product(tiles[names[a]], tiles[names[b]]))
        ok, stats = verify_by_tile_pairs(feats[a], feats[b], ia, ib, tps, MatchingConfig(), rng2)
        if ok.sum():
            pairs[(a, b)] = PairMatches(names[a], names[b], ia[ok], ib[ok], stats)
    tracks = build_tracks([len(f) for f in feats], [(a, b, pm) for (a, b), pm in pairs.items()])
    all_tiles = [t for nm in names for t in tiles[nm]]
    return names, all_tiles, feats, pairs, tracks


def _run(extra_image=False):
    names, tiles, feats, pairs, tracks = _scene(np.random.default_rng(0), extra_image)
    events = []
    sfm = IncrementalSfM(0, names, tiles, feats, pairs, tracks, SfmConfig(), BundleConfig(),
                         EventBus(events.append), seed=0)
    return sfm, sfm.run(), events


def test_flat_tiles_of_a_new_image_are_all_registered():
    sfm, m, _ = _run()
    assert m.stats["tiles_registered"] == m.stats["tiles_total"] == 12, m.stats["unregistered_reasons"]  # 3 x (2 x 2)
    assert m.stats["unregistered_reasons"] == {}
    assert m.stats["flat_tiles_regularised"]["toward_its_image_camera"] >= 1
    assert m.stats["rms_reproj_px"] < 0.3
    # the third image's first registered tile was a flat one (the situation this is about)
    third = [t for t in m.register_order if m.tiles[t].image == "v2.tif"]
    first = third[0]
    o = m.obs
    pts = m.X[np.unique(o.track[(o.tile == first) & o.valid & m.has_point[o.track]])]
    from recon_core.geometry.affine import points_conditioning
    assert points_conditioning(pts) < SfmConfig().min_points_conditioning


def test_a_tile_that_cannot_be_registered_is_named_with_its_reason():
    _, m, events = _run(extra_image=True)
    reasons = m.stats["unregistered_reasons"]
    assert set(reasons) == {t.id for t in m.tiles if t.image == "v3.tif"}
    assert all("correspondences" in r for r in reasons.values())
    warned = [e.text for e in events if isinstance(e, Message) and e.level == "warning"]
    assert all(any(tid in w for w in warned) for tid in reasons)
