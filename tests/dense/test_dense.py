"""Dense matching: conventions and building blocks on data with known answers, then the dense
cloud of the tiny synthetic site against its truth."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from recon_core.config import Config, DenseConfig, SgbmConfig, preset
from recon_core.dense.matchers import MgmMatcher, lr_consistent, make_matcher, run_sgbm, sgbm_params
from recon_core.dense.reconstruct import (
    DenseJob,
    PartnerSpec,
    TileSpec,
    _triangulate,
    disparity_range,
    patch_ncc,
    run_job,
    sample_disparity,
)
from recon_core.geometry import affine
from recon_core.io.site import open_image
from recon_core.model.tiling import Tile
from tests.conftest import write_tiff


def _texture(h, w, seed=0):
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.uniform(0, 255, (h, w)), (0, 0), 1.2)


def test_sgbm_convention_recovers_known_disparity():
    """Rectified image 2 is image 1 shifted by d = x2' - x1' = +6.5 px: SGBM must give d back."""
    big = _texture(140, 260)
    d_true = 6.5
    M = np.float32([[1, 0, d_true], [0, 1, 0]])       # img2(x) = img1(x - d): a match at x1 + d
    left = big.astype(np.uint8)
    right = cv2.warpAffine(big, M, (260, 140), flags=cv2.INTER_CUBIC).astype(np.uint8)
    cfg = SgbmConfig()
    lo, hi = disparity_range(np.array([5.0, 6.0, 7.0, 8.0]), 4.0, 0.0)
    min_d, num_d = sgbm_params(lo, hi)
    assert num_d % 16 == 0 and min_d <= -hi
    D = run_sgbm(left, right, min_d, num_d, cfg)
    d = -D[20:-20, 60:-20]
    assert np.nanmedian(d) == pytest.approx(d_true, abs=0.15)
    # the matcher interface: the project's sign convention, validity from the left-right check
    d2, valid = make_matcher(Config()).match(left, right, lo, hi)
    assert isinstance(make_matcher(Config()), MgmMatcher)          # the default: the paper's MGM
    assert np.nanmedian(d2[20:-20, 60:-20]) == pytest.approx(d_true, abs=0.15)
    assert np.array_equal(valid, np.isfinite(d2)) and valid[20:-20, 60:-20].mean() > 0.8
    with pytest.raises(ValueError, match="unknown stereo matcher"):
        make_matcher(Config().with_overrides({"dense.matcher": "nope"}))


def test_disparity_range_percentiles_and_margins():
    d = np.concatenate([np.linspace(-10, 20, 1000), [500.0]])   # one wild outlier
    lo, hi = disparity_range(d, 8.0, 0.25)
    assert lo < -10 and hi > 20 and hi < 40                          # the outlier is ignored


def test_lr_check_flags_inconsistent_pixels():
    D = np.full((4, 50), 5.0, np.float32)
    Dr = np.full((4, 50), 5.0, np.float32)
    Dr[:, 20:25] = 9.0                                               # right disagrees here
    ok = lr_consistent(D, Dr, 1.0)
    assert ok[:, 30].all() and not ok[:, 26].any()                   # x - D = 21 lands in the bad band
    assert not ok[:, 2].any()                                        # match falls outside the image


def test_sample_disparity_no_blending_across_edges():
    d = np.zeros((10, 10), np.float32)
    d[:, 5:] = 20.0
    d[0, 0] = np.nan
    s = sample_disparity(d, np.array([[2.5, 3.5], [4.6, 3.0], [0.2, 0.2], [11.0, 1.0]]))
    assert s[0] == 0.0                          # smooth: bilinear
    assert s[1] == 20.0                         # across the edge: nearest, never 12
    assert s[2] == 0.0 or np.isnan(s[2])        # next to an invalid sample: nearest
    assert np.isnan(s[3])                       # outside


def test_patch_ncc_follows_the_local_affine_map():
    img = _texture(200, 200, 1).astype(np.float32)
    A = np.array([[0.9, 0.25, 30.0], [-0.2, 1.05, 12.0]])            # partner = warp of reference
    part = cv2.warpAffine(img, A, (220, 220), flags=cv2.INTER_CUBIC)
    p = np.array([[60, 70], [100, 90], [120, 140]])
    q = p @ A[:, :2].T + A[:, 2]
    good = patch_ncc(img, p, part, q, A[:, :2], 2)
    wrong = patch_ncc(img, p, part, q + [7.0, -5.0], A[:, :2], 2)
    assert np.all(good > 0.97) and wrong.max() < 0.8 and wrong.mean() < 0.4


def _cams():
    return np.array([[[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]],
                     [[0.95, 0.1, 0.45, 3.0], [-0.05, 1.0, 0.1, -2.0]],
                     [[1.02, -0.1, -0.4, 1.0], [0.08, 0.97, 0.15, 4.0]]])


def test_track_triangulation_drops_the_bad_view():
    rng = np.random.default_rng(0)
    cams = _cams()
    X = rng.uniform([0, 0, -20], [100, 100, 20], (50, 3))
    x = affine.project(cams, X)
    pix = x[0]
    q1, q2 = x[1].copy(), x[2].copy()
    q2[7] += [6.0, -4.0]                                             # one corrupted link
    best_q = {"b": q1, "c": q2}
    best_cam = {"b": np.ones(50, np.int64), "c": np.full(50, 2, np.int64)}
    Xr, nv, rms, idx, pair = _triangulate(pix, list(cams), best_q, best_cam, max_err=1.0)
    assert len(idx) == 50
    np.testing.assert_allclose(Xr, X[idx], atol=1e-6)
    assert nv[7] == 2 and np.all(nv[np.arange(50) != 7] == 3)


def test_textureless_pair_gives_no_points_and_a_message(tmp_path):
    flat = np.full((120, 120), 900, np.uint16)
    p1 = write_tiff(tmp_path / "a.tif", flat)
    p2 = write_tiff(tmp_path / "b.tif", flat)
    cams = _cams()
    rng = np.random.default_rng(1)
    X = rng.uniform([10, 10, -20], [110, 110, 20], (40, 3))
    x = affine.project(cams, X)
    ref = TileSpec(open_image(p1), Tile("a.tif", 0, 0, 120, 120), cams[0])
    part = TileSpec(open_image(p2), Tile("b.tif", 0, 0, 120, 120), cams[1])
    job = DenseJob(0, ref, (0, 0, 120, 120), [PartnerSpec(part, x[0], x[1])], DenseConfig())
    res = run_job(job)
    assert len(res.xyz) == 0 and res.message and "no dense points" in res.message


def test_dense_tiny_against_truth(tiny_run, tiny_site):
    """Dense cloud mapped to the truth by the affine map fitted on the SPARSE points (test only):
    median |height error| < 0.5 m, and > 80 % of the area seen by >= 2 images covered."""
    import rasterio

    from recon_core.euclidean.dsm import rasterize
    from recon_core.euclidean.georef import frame_for
    from recon_core.synthetic.truth import sparse_vs_truth
    from recon_core.geometry.geodesy import geodetic_to_projected
    from recon_core.io.models import load_dense
    from recon_core.io.raster import Grid

    state, _ = tiny_run
    frame = frame_for(state.gcps)
    fit = sparse_vs_truth(tiny_site, state.models[0], frame)
    cloud = load_dense(state.layout, 0)
    enu = affine.apply_affine_3d(fit["A"], cloud.xyz)
    with rasterio.open(tiny_site / "gt_dsm.tif") as ds:
        gt = ds.read(1).astype(np.float64)
        if ds.nodata is not None and not np.isnan(ds.nodata):
            gt[gt == ds.nodata] = np.nan
        grid = Grid(ds.crs.to_epsg(), ds.transform.c, ds.transform.f, ds.transform.a, ds.width, ds.height)
    xyh = geodetic_to_projected(frame.enu_to_geodetic(enu), grid.crs_epsg)
    H, _ = rasterize(xyh, grid, stat="median")
    valid = np.isfinite(gt)
    err = (H - gt)[valid & np.isfinite(H)]
    coverage = np.isfinite(H[valid]).mean()
    assert np.median(np.abs(err)) < 0.5
    assert coverage > 0.8


def test_dense_summary_accounts_for_every_tile_pair(tiny_run):
    """Each planned tile pair is matched, not needed (the parts the two tiles own do not
    overlap), or skipped with a reason; the streamed PLY holds exactly the counted points."""
    from recon_core.io.ply import open_ply

    state, _ = tiny_run
    d = state.report["stages"]["dense"]["groups"]["0"]
    assert d["pairs_matched"] > 0
    assert d["pairs_matched"] + d["pairs_not_needed"] + len(d["pairs_skipped"]) == d["tile_pairs"]
    assert len(open_ply(state.layout.dense_ply(0))) == d["points"] == sum(d["views_histogram"])
    assert 0 <= d["median_reproj_px"] <= preset("tiny").dense.max_reproj_px


def test_a_float_image_beside_12_bit_counts_keeps_its_contrast_for_matching():
    """The joint tone curve of a tile pair would crush a reflectance image (0..1) beside 12-bit
    counts to black (the trial: the dense cloud fell from 244 k to 97 k points); such a pair gets
    one curve per image, and a pair of one kind keeps its joint curve."""
    from recon_core.dense.reconstruct import to_8bit_pair

    rng = np.random.default_rng(0)
    counts = rng.uniform(200, 1800, (64, 64))
    a8, b8 = to_8bit_pair(counts, counts / 2047.0)
    assert b8.std() > 0.5 * a8.std() and np.corrcoef(a8.ravel(), b8.ravel())[0, 1] > 0.99
    a8, b8 = to_8bit_pair(counts, 1.2 * counts)             # one kind: one curve (gain kept)
    assert b8.mean() > a8.mean() + 5
    dark, bright = counts / 3.0 + 40.0, 1.6 * counts + 100.0  # winter and summer, one kind
    a8, b8 = to_8bit_pair(dark, bright)
    assert b8.mean() > a8.mean() + 40


def test_weak_pair_points_are_the_imprecise_ones_and_only_fill(tiny_run, tiny_site):
    """`tiny` has one small-angle pair among its three views. The two-view points marked weak
    (their pair triangulates > 2x less precisely than the best pair) are the least accurate
    against the ground truth, and a DSM that uses them only where nothing else falls is more
    accurate than one that mixes them in, with the same cells covered."""
    import rasterio

    from recon_core.euclidean.dsm import DsmAccumulator
    from recon_core.euclidean.georef import frame_for
    from recon_core.synthetic.truth import sparse_vs_truth
    from recon_core.geometry.geodesy import geodetic_to_projected
    from recon_core.io.models import load_dense
    from recon_core.io.raster import Grid

    state, _ = tiny_run
    frame = frame_for(state.gcps)
    fit = sparse_vs_truth(tiny_site, state.models[0], frame)
    cloud = load_dense(state.layout, 0)
    assert cloud.weak is not None and 0.02 < cloud.weak.mean() < 0.6
    with rasterio.open(tiny_site / "gt_dsm.tif") as ds:
        gt = ds.read(1).astype(np.float64)
        grid = Grid(ds.crs.to_epsg(), ds.transform.c, ds.transform.f, ds.transform.a, ds.width, ds.height)
    xyh = geodetic_to_projected(frame.enu_to_geodetic(affine.apply_affine_3d(fit["A"], cloud.xyz)),
                                grid.crs_epsg)
    r, c = grid.cell_of(xyh[:, 0], xyh[:, 1])
    inside = grid.contains(r, c)
    e = np.full(len(xyh), np.nan)
    e[inside] = np.abs(xyh[inside, 2] - gt[r[inside], c[inside]])
    two = cloud.n_views == 2
    assert np.nanmedian(e[cloud.weak]) > 2.0 * np.nanmedian(e[two & ~cloud.weak])

    def dsm(tier):
        acc = DsmAccumulator(grid)
        acc.add(xyh, tier)
        return acc.finish()[0]
    mixed, tiered = dsm(None), dsm(cloud.weak)
    assert np.array_equal(np.isfinite(mixed), np.isfinite(tiered))
    ok = np.isfinite(gt) & np.isfinite(tiered)
    assert np.median(np.abs(tiered - gt)[ok]) < 0.8 * np.median(np.abs(mixed - gt)[ok])


def test_triangulation_removes_each_cameras_within_tile_correction():
    """Dense points are seen by each tile camera as the SfM's tie points are: a pixel minus its
    tile's correction field (CorrectionField), so that pixels displaced by the field triangulate
    to the true point, and without the fields they do not."""
    from recon_core.dense.reconstruct import _triangulate
    from recon_core.model.sparse_model import CorrectionField

    rng = np.random.default_rng(5)
    X = rng.uniform(-200, 200, (500, 3)) * [1, 1, 0.1]
    P0 = np.array([[2.0, 0.0, 0.1, 500.0], [0.0, 2.0, -0.3, 500.0]])
    P1 = np.array([[1.9, 0.2, 0.8, 480.0], [-0.1, 2.0, 0.2, 510.0]])
    f0 = CorrectionField(np.array([500.0, 500.0]), 500.0, rng.normal(0, 0.05, (6, 2)))
    f1 = CorrectionField(np.array([500.0, 500.0]), 500.0, rng.normal(0, 0.05, (6, 2)))

    def seen(P, f):
        a = X @ P[:, :3].T + P[:, 3]
        x = a.copy()
        for _ in range(20):                      # pixel x with x - f(x) = P X
            x = a + f(x)
        return x

    x0, x1 = seen(P0, f0), seen(P1, f1)
    args = (x0, [P0, P1], {"b": x1}, {"b": np.ones(len(X), np.int64)}, 10.0)
    Xc, _, _, idx, _ = _triangulate(*args, fields=[f0, f1])
    np.testing.assert_allclose(Xc, X[idx], atol=1e-6)
    Xr, _, _, idx_r, _ = _triangulate(*args)
    assert np.abs(Xr - X[idx_r]).max() > 0.01
