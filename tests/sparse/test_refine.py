"""Tie-point refinement against an exactly known warp between two images."""

import cv2
import numpy as np

from recon_core.sparse.refine import refine_points, smooth


def _texture(rng, n=900):
    base = cv2.GaussianBlur(rng.normal(size=(n, n)).astype(np.float32), (0, 0), 2.0)
    return base * 400 + 1000


def _view(base, M, shape):
    """Image whose pixel x samples base at M @ [x, 1] (bicubic, as a sensor sees a smooth scene)."""
    return cv2.warpAffine(base, M, shape[::-1], flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP)


def _pair(seed=0):
    rng = np.random.default_rng(seed)
    base = _texture(rng)
    M1 = np.array([[1.0, 0.0, 100.0], [0.0, 1.0, 100.0]])
    th = np.deg2rad(25.0)
    L = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]]) @ np.diag([1.08, 0.93])
    M2 = np.c_[L, [180.0, 60.0]]
    shape = (600, 600)
    img1, img2 = _view(base, M1, shape), _view(base, M2, shape)
    img1 += rng.normal(0, 4, shape).astype(np.float32)
    img2 += rng.normal(0, 4, shape).astype(np.float32)
    # base point b = M1 [x1, 1] = M2 [x2, 1]  ->  x2 = L^-1 (M1 [x1, 1] - t2)
    Linv = np.linalg.inv(L)
    x1 = rng.uniform(60, 540, (400, 2))
    b = x1 @ M1[:, :2].T + M1[:, 2]
    x2 = (b - M2[:, 2]) @ Linv.T
    keep = (x2 > 40).all(1) & (x2 < 560).all(1)
    A = Linv @ M1[:, :2]                    # d x2 = A d x1
    return img1, img2, x1[keep], x2[keep], A, rng


def test_refinement_recovers_the_true_positions_from_sift_sized_errors():
    img1, img2, x1, x2, A, rng = _pair()
    start = x2 + rng.normal(0, 0.4, x2.shape)
    before = np.sqrt(np.mean((start - x2) ** 2))
    r = refine_points(smooth(img1, 0.7), x1, smooth(img2, 0.7), start, A)
    assert r.ok.mean() > 0.95
    after = np.sqrt(np.mean((r.xy[r.ok] - x2[r.ok]) ** 2))
    assert before > 0.35 and after < 0.05, (before, after)


def test_refinement_refuses_flat_or_unrelated_patches_and_keeps_their_positions():
    img1, img2, x1, x2, A, rng = _pair(1)
    start = x2 + rng.normal(0, 0.4, x2.shape)
    flat = np.full_like(img2, 1000.0)
    r = refine_points(img1, x1, flat, start, A)
    assert not r.ok.any() and np.array_equal(r.xy, start)
    other = _view(_texture(np.random.default_rng(99)), np.array([[1.0, 0, 0], [0, 1.0, 0]]), img2.shape)
    r = refine_points(img1, x1, other, start, A)
    assert r.ok.mean() < 0.05
    assert np.array_equal(r.xy[~r.ok], start[~r.ok])
    # a point whose patch leaves the image is not refined
    r = refine_points(img1, np.array([[2.0, 300.0]]), img2, np.array([[300.0, 300.0]]), A)
    assert not r.ok[0]


def test_refine_tracks_reads_by_block_and_moves_only_non_reference_observations(tmp_path, monkeypatch):
    import rasterio

    from recon_core.io.site import open_image
    from recon_core.sparse.features import ImageFeatures
    from recon_core.sparse.refine import refine_tracks
    from recon_core.sparse.tracks import Tracks

    img1, img2, x1, x2, A, rng = _pair(2)
    infos = []
    for k, a in enumerate((img1, img2)):
        p = tmp_path / f"im{k}.tif"
        with rasterio.open(p, "w", driver="GTiff", width=a.shape[1], height=a.shape[0], count=1,
                           dtype="uint16") as ds:
            ds.write(np.clip(np.round(a), 0, 65535).astype(np.uint16), 1)
        infos.append(open_image(p))
    n = len(x1)
    start = x2 + rng.normal(0, 0.4, x2.shape)
    z = np.zeros(n, np.float32)

    def feats(xy):
        return ImageFeatures("x", xy.copy(), np.zeros((n, 128), np.uint8), z, z, z.astype(np.uint8))

    # features listed in another order than the tracks, to check the bookkeeping
    perm = rng.permutation(n)
    f1, f2 = feats(x1), feats(start[perm])
    inv = np.argsort(perm)
    tracks = Tracks(np.r_[np.zeros(n), np.ones(n)].astype(np.int64), np.r_[np.arange(n), inv].astype(np.int64),
                    np.r_[np.arange(n), np.arange(n)].astype(np.int64), n)
    out, st = refine_tracks(infos, [f1, f2], tracks, block=128)      # several blocks per image
    assert np.array_equal(out[0].xy, x1)                              # the reference does not move
    moved = out[1].xy[inv]
    assert st.candidates == n and st.refined > 0.9 * n
    before = np.sqrt(np.mean((start - x2) ** 2))
    after = np.sqrt(np.mean((moved - x2) ** 2))
    assert after < 0.2 * before, (before, after)
    # patches are refined in chunks of bounded size: the same positions
    import recon_core.sparse.refine as refine_mod
    monkeypatch.setattr(refine_mod, "CHUNK", 37)
    again, _ = refine_tracks(infos, [f1, f2], tracks, block=128)
    np.testing.assert_array_equal(again[1].xy, out[1].xy)


def test_across_dates_only_the_first_view_of_each_other_group_is_matched_to_the_track(tmp_path):
    """Three views, the second and third of a later date: the second is refined against the
    first, the third against the second (same date), and all land on the truth."""
    import rasterio

    from recon_core.io.site import open_image
    from recon_core.sparse.features import ImageFeatures
    from recon_core.sparse.refine import refine_tracks
    from recon_core.sparse.tracks import Tracks

    rng = np.random.default_rng(5)
    base = _texture(rng)
    shape = (500, 500)
    views = []
    for k, (th, sx, sy, tx, ty) in enumerate([(0, 1, 1, 100, 100), (20, 1.05, 0.95, 160, 60),
                                               (-15, 0.96, 1.04, 60, 180)]):
        t = np.deg2rad(th)
        L = np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]]) @ np.diag([sx, sy])
        M = np.c_[L, [tx, ty]]
        a = _view(base, M, shape) + rng.normal(0, 4, shape).astype(np.float32)
        p = tmp_path / f"im{k}.tif"
        with rasterio.open(p, "w", driver="GTiff", width=500, height=500, count=1, dtype="uint16") as ds:
            ds.write(np.clip(np.round(a), 0, 65535).astype(np.uint16), 1)
        views.append((open_image(p), M))
    b = rng.uniform(250, 450, (300, 2))                      # base points seen by all three
    truth = [np.linalg.solve(M[:, :2], (b - M[:, 2]).T).T for _, M in views]
    n = len(b)
    z = np.zeros(n, np.float32)
    start = [truth[0]] + [t + rng.normal(0, 0.4, t.shape) for t in truth[1:]]
    feats = [ImageFeatures("x", s.copy(), np.zeros((n, 128), np.uint8), z, z, z.astype(np.uint8))
             for s in start]
    tracks = Tracks(np.repeat(np.arange(3), n), np.tile(np.arange(n), 3), np.tile(np.arange(n), 3), n)
    out, st = refine_tracks([v[0] for v in views], feats, tracks, image_groups=[0, 1, 1])
    assert set(st.pairs) == {"im0.tif|im1.tif", "im1.tif|im2.tif"}     # im2 never against im0
    assert np.array_equal(out[0].xy, truth[0])
    for k in (1, 2):
        before = np.sqrt(np.mean((start[k] - truth[k]) ** 2))
        after = np.sqrt(np.mean((out[k].xy - truth[k]) ** 2))
        assert after < 0.25 * before, (k, before, after)
