"""Features and matching on images with a known geometric relation: a textured image and a
copy warped by a known 2D affine map (what two views of flat ground are)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from recon_core.config import FeatureConfig
from recon_core.io.site import open_image
from recon_core.sparse.features import detect_image, detect_overview, group_tone_curves, tone_curve_for
from recon_core.sparse.matching import coarse_link, match_descriptors
from tests.conftest import write_tiff

A_TRUE = np.array([[0.97, 0.12, 25.0], [-0.10, 1.02, -14.0]])   # image b pixel -> image a pixel


def _pair(tmp_path):
    rng = np.random.default_rng(0)
    base = cv2.GaussianBlur(rng.uniform(0, 2047, (700, 700)), (0, 0), 2.0)
    blobs = cv2.GaussianBlur((rng.uniform(size=(700, 700)) > 0.995).astype(float) * 4000, (0, 0), 3.0)
    a = (base + blobs).astype(np.uint16)
    # b(x) = a(A x): warp a by the inverse map so that A_TRUE sends b's pixels to a's
    b = cv2.warpAffine(a.astype(np.float32), A_TRUE, (640, 640),
                       flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP).astype(np.uint16)
    write_tiff(tmp_path / "a.tif", a[:640, :640])
    write_tiff(tmp_path / "b.tif", b)
    return open_image(tmp_path / "a.tif"), open_image(tmp_path / "b.tif")


def test_detection_by_blocks_equals_one_block_and_has_no_duplicates(tmp_path):
    a, _ = _pair(tmp_path)
    tone = tone_curve_for([a])
    one = detect_image(a, FeatureConfig(detect_block=4096), tone)
    blocks = detect_image(a, FeatureConfig(detect_block=200), tone)
    # deduplicated: no two keypoints share position and descriptor (one position may carry
    # several SIFT orientations, each with its own descriptor)
    key = np.concatenate([np.round(blocks.xy * 100).astype(np.int64), blocks.desc.astype(np.int64)], axis=1)
    assert len(np.unique(key, axis=0)) == len(blocks)
    # block borders (48 px margins) move few keypoints: most positions are found by both
    k1 = {tuple(v) for v in np.round(one.xy).astype(int)}
    k2 = {tuple(v) for v in np.round(blocks.xy).astype(int)}
    assert len(k1 & k2) > 0.8 * min(len(k1), len(k2)) and len(one) > 200
    assert blocks.desc.dtype == np.uint8 and np.all((blocks.xy >= -0.5) & (blocks.xy <= 639.5))


def test_detection_spilled_as_it_goes_equals_detection_in_memory(tmp_path):
    """With `spill`, each block's descriptors go to the file as they are detected (a 40,000 px
    scene's would not fit in memory): the same keypoints, the descriptors a read-only map of
    the file, also when the keypoint budget drops some."""
    a, _ = _pair(tmp_path)
    tone = tone_curve_for([a])
    for k, cfg in enumerate((FeatureConfig(detect_block=320), FeatureConfig(detect_block=320, max_features_per_mpx=100))):
        mem = detect_image(a, cfg, tone)
        disk = detect_image(a, cfg, tone, spill=tmp_path / f"{k}.desc")
        assert isinstance(disk.desc, np.memmap) and not disk.desc.flags.writeable
        assert (tmp_path / f"{k}.desc").stat().st_size == 128 * len(disk) and len(disk) > 400
        for f in ("xy", "desc", "scale", "response", "gray"):
            assert np.array_equal(np.asarray(getattr(mem, f)), np.asarray(getattr(disk, f))), f
    assert len(mem) == 500 and sorted(p.name for p in tmp_path.glob("*.desc*")) == ["0.desc", "1.desc"]


def test_the_tone_curve_and_the_overview_features_read_a_bounded_overview(tmp_path, monkeypatch):
    """A tone curve and the coarse link's features read the image decimated to at most
    OVERVIEW_MAX_PX pixels, however large the image (a 40,000 px scene at factor 8 was 25 Mpx,
    and SIFT's pyramid of it several GB)."""
    import recon_core.io.site as site_io
    import recon_core.sparse.features as features

    a, _ = _pair(tmp_path)
    reads, read = [], site_io.read_window

    def spy(image, c0, r0, w, h, **kw):
        out = read(image, c0, r0, w, h, **kw)
        reads.append(out.size)
        return out

    monkeypatch.setattr(site_io, "read_window", spy)
    monkeypatch.setattr(features, "OVERVIEW_MAX_PX", 64 * 64)
    lo_hi = tone_curve_for([a])
    assert reads and max(reads) <= 64 * 64 and lo_hi.hi > lo_hi.lo
    reads.clear()
    xy, desc = detect_overview(a, 2, lo_hi)
    assert reads and max(reads) <= 64 * 64 and len(xy) == len(desc) > 0
    assert np.all((xy >= -0.5) & (xy <= 639.5))                   # in full-image pixels


def test_overview_link_recovers_the_known_affine_map(tmp_path):
    a, b = _pair(tmp_path)
    tone = tone_curve_for([a, b])
    link = coarse_link("a", detect_overview(a, 2, tone), "b", detect_overview(b, 2, tone))
    assert link is not None and link.n_inliers >= 12
    corners = np.array([[0, 0], [639, 0], [639, 639], [0, 639]], float)
    pred = corners @ link.A_ji[:, :2].T + link.A_ji[:, 2]
    true = corners @ A_TRUE[:, :2].T + A_TRUE[:, 2]
    assert np.abs(pred - true).max() < 4.0                   # a few full-resolution pixels


def test_descriptor_matching_ratio_and_mutual():
    rng = np.random.default_rng(2)
    d1 = rng.integers(0, 255, (50, 128)).astype(np.uint8)
    perm = rng.permutation(50)
    d2 = np.clip(d1[perm].astype(int) + rng.integers(-3, 4, (50, 128)), 0, 255).astype(np.uint8)
    d2 = np.vstack([d2, d2[:5]])                             # 5 ambiguous twins fail the ratio test
    i, j = match_descriptors(d1, d2, 0.8, True)
    assert len(i) == 45 and np.array_equal(perm[j], i)


def test_a_float32_image_among_uint16_ones_gets_its_own_stretch_and_its_keypoints(tmp_path):
    """A reflectance image (float32, 0-1) in a group of uint16 counts: with one shared tone curve
    it maps to black (no keypoint) and the run later blames a GCP. It gets its own curve, a
    warning naming it, and about as many keypoints as the same scene in counts."""
    a, b = _pair(tmp_path)
    import rasterio

    with rasterio.open(b.path) as ds:
        counts = ds.read(1)
    write_tiff(tmp_path / "c.tif", (counts / 2047.0).astype(np.float32))
    c = open_image(tmp_path / "c.tif")
    curves, warnings = group_tone_curves([a, b, c])
    assert curves[0] is curves[1] and curves[2] is not curves[0]
    assert len(warnings) == 1 and warnings[0].startswith("c.tif") and "float32" in warnings[0]
    shared = tone_curve_for([a, b, c])
    assert len(detect_image(c, FeatureConfig(), shared)) < 10          # what used to happen
    n_b, n_c = len(detect_image(b, FeatureConfig(), curves[1])), len(detect_image(c, FeatureConfig(), curves[2]))
    assert n_c > 0.7 * n_b and n_b > 200
    # same products: no warning, one curve
    curves, warnings = group_tone_curves([a, b])
    assert not warnings and curves[0] is curves[1]
    # an image with a much wider range (16-bit counts among 11-bit ones) is the one named
    write_tiff(tmp_path / "d.tif", np.clip(counts.astype(np.float64) * 30, 0, 65535).astype(np.uint16))
    curves, warnings = group_tone_curves([a, b, open_image(tmp_path / "d.tif")])
    assert len(warnings) == 1 and warnings[0].startswith("d.tif") and curves[0] is curves[1]


def test_a_float_image_with_lines_of_no_measurement_keeps_its_tie_points(tmp_path):
    """Every 10th row NaN (dropped lines of a float product): its thin gaps are filled for the
    detection, so it keeps about the keypoints and matches of the same image without them (it
    lost 40 % of its keypoints, and more of its matches, before); the group's warning names it."""
    a, b = _pair(tmp_path)
    import rasterio

    with rasterio.open(b.path) as ds:
        counts = ds.read(1).astype(np.float32)
    write_tiff(tmp_path / "clean.tif", counts)
    holes = counts.copy()
    holes[::10] = np.nan
    holes[300:340, 300:340] = np.inf                      # a wide gap stays a gap
    write_tiff(tmp_path / "lines.tif", holes)
    clean, lines = open_image(tmp_path / "clean.tif"), open_image(tmp_path / "lines.tif")
    tone = tone_curve_for([clean])
    fa = detect_image(a, FeatureConfig(), tone_curve_for([a]))
    fc, fl = detect_image(clean, FeatureConfig(), tone), detect_image(lines, FeatureConfig(), tone)
    assert len(fl) > 0.85 * len(fc)
    inside = (fl.xy[:, 0] > 305) & (fl.xy[:, 0] < 335) & (fl.xy[:, 1] > 305) & (fl.xy[:, 1] < 335)
    assert not inside.any()
    ma = match_descriptors(fa.desc, fc.desc, 0.8, True)[0]
    mb = match_descriptors(fa.desc, fl.desc, 0.8, True)[0]
    assert len(mb) > 0.8 * len(ma) and len(ma) > 200
    _, warnings = group_tone_curves([clean, lines])
    assert len(warnings) == 1 and warnings[0].startswith("lines.tif") and "NaN or infinite" in warnings[0]


@pytest.mark.parametrize("mutual", [False, True])
def test_match_descriptors_is_opencvs_brute_force_ratio_test(mutual):
    """The BLAS distance matrix gives the matches OpenCV's exact brute force gives (ratio test on
    distances, mutual check), on SIFT-like uint8 descriptors with planted near-duplicates."""
    rng = np.random.default_rng(7)
    d2 = rng.integers(0, 140, (900, 128)).astype(np.uint8)
    d1 = rng.integers(0, 140, (300, 128)).astype(np.uint8)
    d1[:150] = np.clip(d2[rng.choice(900, 150, replace=False)].astype(int)
                       + rng.integers(-6, 7, (150, 128)), 0, 255).astype(np.uint8)

    def bf(a, b):
        out = np.full(len(a), -1)
        for q, m in enumerate(cv2.BFMatcher(cv2.NORM_L2).knnMatch(a.astype(np.float32), b.astype(np.float32), k=2)):
            if m[0].distance < 0.8 * m[1].distance:
                out[q] = m[0].trainIdx
        return out
    fwd = bf(d1, d2)
    i1 = np.flatnonzero(fwd >= 0)
    if mutual:
        back = bf(d2, d1)
        i1 = i1[back[fwd[i1]] == i1]
    a, b = match_descriptors(d1, d2, 0.8, mutual)
    assert len(i1) >= 140
    assert np.array_equal(a, i1) and np.array_equal(b, fwd[i1])


def test_matching_on_spilled_descriptors_equals_matching_in_memory(tmp_path):
    from recon_core.config import MatchingConfig
    from recon_core.model.tiling import tile_image
    from recon_core.sparse.matching import match_pair

    a, b = _pair(tmp_path)
    tone = tone_curve_for([a, b])
    fa, fb = detect_image(a, FeatureConfig(), tone), detect_image(b, FeatureConfig(), tone)
    link = coarse_link("a", detect_overview(a, 2, tone), "b", detect_overview(b, 2, tone))
    ta, tb = tile_image(a.name, 640, 640, 300), tile_image(b.name, 640, 640, 300)
    mem = match_pair(fa, fb, link, ta, tb, MatchingConfig(), np.random.default_rng(0))
    sa = detect_image(a, FeatureConfig(), tone, spill=tmp_path / "a.desc")
    sb = detect_image(b, FeatureConfig(), tone, spill=tmp_path / "b.desc")
    assert isinstance(sa.desc, np.memmap) and not sa.desc.flags.writeable
    assert np.array_equal(np.asarray(sa.desc), fa.desc) and np.array_equal(sa.xy, fa.xy)
    disk = match_pair(sa, sb, link, ta, tb, MatchingConfig(), np.random.default_rng(0))
    assert mem.n > 100
    assert np.array_equal(mem.idx_i, disk.idx_i) and np.array_equal(mem.idx_j, disk.idx_j)


def test_the_sparse_stage_spills_descriptors_to_out_and_removes_them(tiny_site, tmp_path):
    from recon_core.config import preset
    from recon_core.events import EventBus, StageProgress
    from recon_core.pipeline import run

    out = tmp_path / "out"
    seen = []

    def listen(ev):
        if isinstance(ev, StageProgress) and ev.stage == "matching":
            seen.append(sorted(p.name for d in out.glob(".sparse_desc_*") for p in d.iterdir()))

    state = run(tiny_site, out, preset("tiny"), until="sparse", bus=EventBus(listen))
    n_images = len(state.groups[0].images)
    assert seen and all(s == [f"{k}.desc" for k in range(n_images)] for s in seen)
    assert not list(out.glob(".sparse_desc_*")) and state.models
