"""Fusing date groups into one DSM: the best-checked group wins each cell it sees, the others
fill its holes; each group's own DSM and scores are kept."""

from __future__ import annotations

import json

import numpy as np
import pytest

from recon_core.euclidean.dsm_stage import fuse_groups, group_quality, rank_groups
from recon_core.io.layout import OutLayout
from recon_core.io.raster import read_dsm


def test_group_noise_splits_the_groups_disagreement():
    """Three matchings of one surface with noise 0.1, 0.2 and 0.4 m, one of them also offset
    by a smooth tilt: the three-cornered hat finds each noise within 15 %; two groups share
    their disagreement equally; a group that overlaps none gets None."""
    from recon_core.euclidean.dsm_stage import group_noise

    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:300, 0:400].astype(np.float32)
    truth = 0.01 * xx + 8.0 * (((xx // 40) + (yy // 40)) % 3 == 0)
    D = {g: (truth + rng.normal(0, s, truth.shape)).astype(np.float32)
         for g, s in zip((0, 1, 2), (0.1, 0.2, 0.4))}
    D[2] += (0.002 * xx).astype(np.float32)
    n = group_noise(D, correct_block=32)
    for g, s in zip((0, 1, 2), (0.1, 0.2, 0.4)):
        assert n[g] == pytest.approx(s, rel=0.15), n
    two = group_noise({0: D[0], 1: D[1]}, correct_block=32)
    assert two[0] == two[1] == pytest.approx(np.sqrt((0.1 ** 2 + 0.2 ** 2) / 2), rel=0.1)
    far = np.full(truth.shape, np.nan, np.float32)
    far[:5, :5] = 1.0
    assert group_noise({0: D[0], 1: D[1], 5: far}, correct_block=32)[5] is None


def _tilted_views(theta_deg: float, n: int = 2, gsd: float = 1.0) -> list[np.ndarray]:
    """n orthographic views (2 x 4, pixels of `gsd` metres) spread evenly over theta degrees of
    tilt about the x axis: an image pair of intersection angle theta when n = 2."""
    out = []
    for phi in np.radians(np.linspace(-theta_deg / 2, theta_deg / 2, n)):
        out.append(np.array([[1.0, 0, 0, 0], [0, np.cos(phi), np.sin(phi), 0]]) / gsd)
    return out


def test_views_spread_is_the_textbook_height_precision():
    """Two views of intersection angle theta: a pixel of matching error moves the point by
    1 / (sqrt(2) sin(theta / 2)) metres along the height (the worst direction); a nadir view
    between them adds nothing to the height, a third tilted one does; a finer pixel scales it."""
    from recon_core.geometry.affine import views_spread

    for theta in (6.0, 15.0, 30.0):
        want = 1.0 / (np.sqrt(2) * np.sin(np.radians(theta / 2)))
        assert views_spread(_tilted_views(theta)) == pytest.approx(want, rel=1e-9)
    assert views_spread(_tilted_views(30.0, 3)) == pytest.approx(views_spread(_tilted_views(30.0)))
    assert views_spread(_tilted_views(30.0) + _tilted_views(20.0)[:1]) < views_spread(_tilted_views(30.0))
    assert views_spread(_tilted_views(30.0, gsd=0.5)) == pytest.approx(0.5 * views_spread(_tilted_views(30.0)))
    assert views_spread(_tilted_views(0.0)) == float("inf") or views_spread(_tilted_views(0.0)) > 1e12


def test_group_geometry_reads_the_upgraded_views():
    """A group's geometry is the spread of its images' views (one per image: the median of its
    tiles' cameras) in the metric frame: the same whatever affine frame the cameras are in,
    once their H_A maps it; a group of one image is left out."""
    from types import SimpleNamespace

    from recon_core.euclidean.dsm_stage import group_geometry
    from recon_core.geometry.affine import views_spread

    rng = np.random.default_rng(1)
    A = np.eye(4)
    A[:3] = rng.normal(size=(3, 4))                 # an affine frame: X_aff = A X_metric
    H = np.linalg.inv(A)                            # the upgrade: X_metric = H X_aff

    def model(theta, images):
        views = _tilted_views(theta, len(images))
        tiles, cams = [], []
        for k, im in enumerate(images):
            for _ in range(3):                      # three tiles per image, slightly different
                tiles.append(SimpleNamespace(image=im))
                P = views[k] + np.r_[0, 0, 0, rng.normal()][None] * [[1], [0]]
                cams.append(P @ np.linalg.inv(A))   # the same camera seen in the affine frame
        return SimpleNamespace(registered=np.ones(len(tiles), bool), tiles=tiles, cams=np.array(cams))

    geo = group_geometry({0: model(24.0, ["a", "b", "c"]), 1: model(9.0, ["d", "e"]),
                          2: model(20.0, ["f"])}, {0: H, 1: H, 2: H})
    assert set(geo) == {0, 1}
    assert geo[0] == pytest.approx(views_spread(_tilted_views(24.0, 3)), rel=1e-6)
    assert geo[1] == pytest.approx(views_spread(_tilted_views(9.0)), rel=1e-6)


def test_noise_from_geometry_is_not_fooled_by_a_group_between_two_others():
    """Group 1's errors are half group 0's and half group 2's (it sees the same hard places as
    both: errors correlated between groups, as measured on wide3), so it agrees best with both
    although group 0 is the most precise. A per-group split of the disagreement puts group 1
    first; one matching precision times each group's geometry (here in the truth's ratio)
    ranks them as the truth does and recovers the precision. With independent noise
    proportional to the geometry it finds each group's noise within 10 %, two groups
    included (a split can only share their disagreement)."""
    from recon_core.euclidean.dsm_stage import group_noise

    rng = np.random.default_rng(2)
    yy, xx = np.mgrid[0:300, 0:400].astype(np.float32)
    truth = 0.01 * xx + 8.0 * (((xx // 40) + (yy // 40)) % 3 == 0)
    n0, n2 = rng.normal(0, 0.3, truth.shape), rng.normal(0, 0.9, truth.shape)
    e = {0: n0, 1: 0.5 * n0 + 0.5 * n2, 2: n2}
    D = {g: (truth + e[g]).astype(np.float32) for g in e}
    true_sd = {g: float(np.std(e[g])) for g in e}
    split = group_noise(D, correct_block=32)
    assert min(split, key=split.get) == 1                 # the split is fooled
    geo = {0: 1.0, 1: true_sd[1] / true_sd[0], 2: 3.0}
    model = group_noise(D, correct_block=32, geometry=geo)
    assert sorted(model, key=model.get) == [0, 1, 2]
    # independent noise in proportion to the geometry: each found within 10 %
    k = 0.25
    geo = {0: 1.0, 1: 1.6, 2: 3.0}
    D = {g: (truth + rng.normal(0, k * a, truth.shape)).astype(np.float32) for g, a in geo.items()}
    model = group_noise(D, correct_block=32, geometry=geo)
    for g, a in geo.items():
        assert model[g] == pytest.approx(k * a, rel=0.1), model
    two = group_noise({0: D[0], 2: D[2]}, correct_block=32, geometry=geo)
    assert two[0] == pytest.approx(k, rel=0.1) and two[2] == pytest.approx(3 * k, rel=0.1)
    # a group with no overlap still gets its noise from the shared precision
    far = np.full(truth.shape, np.nan, np.float32)
    far[:5, :5] = 1.0
    assert group_noise({0: D[0], 2: D[2], 5: far}, correct_block=32,
                       geometry={**geo, 5: 2.0})[5] == pytest.approx(2 * k, rel=0.1)


def test_rank_and_fuse():
    assert rank_groups([0, 1, 2], {0: 0.8, 2: 0.3}, {0: 10, 1: 99, 2: 5}) == [2, 0, 1]
    assert rank_groups([0, 1], {}, {0: 10, 1: 99}) == [1, 0]
    # one joint upgrade gives every group the same check figure: the noisier DSM goes last,
    # and with equal noise (two groups) the one with more precise cells goes first
    assert rank_groups([0, 1], {0: 0.2, 1: 0.2}, {0: 99, 1: 10}, {0: 0.3, 1: 0.1}) == [1, 0]
    assert rank_groups([0, 1], {0: 0.2, 1: 0.2}, {0: 10, 1: 99}, {0: 0.2, 1: 0.2}) == [1, 0]
    a = np.array([[1.0, np.nan], [np.nan, np.nan]])
    b = np.array([[5.0, 2.0], [np.nan, 3.0]])
    H, src = fuse_groups([a, b])
    np.testing.assert_array_equal(H, [[1.0, 2.0], [np.nan, 3.0]])
    np.testing.assert_array_equal(src, [[0, 1], [-1, 1]])
    up = {"groups": {"0": {"stats": {"check": {"n": 3, "rmse_U_m": 0.9}}},
                     "1": {"stats": {"check": {"n": 0}, "loo": {"n": 5, "rmse_U_m": 0.4}}},
                     "2": {"error": "group 2: too few control GCPs"}}}
    assert group_quality(up) == {0: 0.9, 1: 0.4}


@pytest.fixture(scope="module")
def tiny2_run(tmp_path_factory):
    from recon_core.events import EventBus
    from recon_core.pipeline import run
    from recon_core.synthetic.generator import generate_site

    root = tmp_path_factory.mktemp("tiny2")
    generate_site(root / "site", preset="tiny2", seed=0)
    events = []
    state = run(root / "site", root / "out", resume=False, bus=EventBus(events.append))
    state.events = events
    return state


def test_date_groups_are_reconstructed_in_one_frame_and_upgraded_by_one_map(tiny2_run):
    """The joint reconstruction: each group keeps its own tiles and points, in one shared frame
    (a GCP triangulated from either group's cameras alone lands on the same affine point),
    upgraded by one H_A; ICP, which only sees seasonal differences then, is not applied."""
    from recon_core.euclidean.georef import triangulate_gcp

    state = tiny2_run
    m0, m1 = state.models[0], state.models[1]
    assert m0.stats["joint"] == m1.stats["joint"]
    assert set(m0.images) | set(m1.images) == set(m0.stats["joint"]["images"])
    assert not set(m0.images) & set(m1.images)
    assert {t.image for t in m0.tiles} == set(m0.images) and {t.image for t in m1.tiles} == set(m1.images)
    maps, _ = state.upgrade
    assert maps[0].same(maps[1])
    # metres, through the one upgrade. The GCPs' true image positions (the site's file has
    # 0.3 px of click noise, which each group's two views of small base turn into ~0.9 m of
    # height and ~0.5 m horizontally) leave only the two groups' frames to disagree; separate
    # reconstructions would differ by an arbitrary affine map
    truth = json.loads((state.site.root / "truth" / "gcps_truth.json").read_text())["gcps"]
    gaps = []
    for g in truth:
        a, b = triangulate_gcp(m0, g["true_observations"]), triangulate_gcp(m1, g["true_observations"])
        if a.xyz is not None and b.xyz is not None:
            gaps.append(maps[0](a.xyz[None])[0] - maps[0](b.xyz[None])[0])
    gaps = np.array(gaps)
    assert len(gaps) >= 4 and np.median(np.linalg.norm(gaps, axis=1)) < 0.3
    assert np.median(np.linalg.norm(gaps[:, :2], axis=1)) < 0.1
    rep = json.loads(state.layout.report.read_text())["stages"]
    assert "joint" in rep["upgrade"]
    assert rep["dsm"]["fusion"]["joint"] and not rep["dsm"]["fusion"]["icp"]["1"]["applied"]


def test_a_joint_run_reports_each_tile_and_model_in_its_own_group(tiny2_run):
    from recon_core.events import BundleAdjusted, ModelUpdated, StageDone, TileRegistered

    state = tiny2_run
    group_of = {im.name: g.index for g in state.groups for im in g.images}
    tiles = [e for e in state.events if isinstance(e, TileRegistered)]
    assert tiles and all(e.group == group_of[e.image] for e in tiles)
    assert all(e.total_tiles == len(state.models[e.group].tiles) for e in tiles)
    for g in (0, 1):                          # registration order counted within the group
        assert sorted({e.order for e in tiles if e.group == g}) == list(range(len(state.models[g].tiles)))
    last = {}
    for e in state.events:
        if isinstance(e, ModelUpdated):
            last[e.group] = e
    assert set(last) == {0, 1}
    for g, e in last.items():
        m = state.models[g]
        assert {m.tiles[t].id for t in range(len(m.tiles)) if m.registered[t]} == set(e.cameras)
        np.testing.assert_array_equal(np.sort(e.ids), m.point_ids())
    done = [e.group for e in state.events if isinstance(e, StageDone) and e.stage == "sparse"
            and e.group is not None]
    assert sorted(done) == [0, 1]
    # each adjustment is told to both groups, once marked as the original (counted once)
    ba = [e for e in state.events if isinstance(e, BundleAdjusted)]
    firsts = [e for e in ba if not e.repeat]
    assert len(ba) == 2 * len(firsts) and {e.group for e in firsts} == {0}
    assert {e.group for e in ba if e.repeat} == {1}


def test_a_joint_model_splits_and_merges_back(tiny2_run):
    from recon_core.model.sparse_model import merge_joint
    from recon_core.sparse.stage import split_model

    m0, m1 = tiny2_run.models[0], tiny2_run.models[1]
    merged = merge_joint([m0, m1])
    assert merged.images == m0.images + m1.images and len(merged.tiles) == len(m0.tiles) + len(m1.tiles)
    again = split_model(merged, 1, m1.images)
    np.testing.assert_array_equal(again.cams, m1.cams)
    np.testing.assert_array_equal(again.has_point, m1.has_point)
    np.testing.assert_array_equal(again.obs.tile, m1.obs.tile)
    assert merge_joint([m0]) is None


def test_two_groups_fused_by_quality_with_their_own_dsms_and_scores(tiny2_run):
    state = tiny2_run
    lay = state.layout
    rep = json.loads(lay.report.read_text())["stages"]
    d = rep["dsm"]
    assert set(d["groups"]) == {"0", "1"} and lay.group_dsms() == [0, 1]
    q = {int(g): v["quality_check_rmse_U_m"] for g, v in d["groups"].items()}
    assert d["group_order"] == sorted(q, key=q.get)                        # best checked first
    best = d["group_order"][0]
    H, grid = read_dsm(lay.dsm)
    Hb, grid_b = read_dsm(lay.group_dsm(best))
    assert grid == grid_b
    # every cell the best group saw keeps its value, or the weighted mean of the groups that
    # agree with it within the fusion's tolerance (hole filling, done on each DSM separately,
    # only touches cells without a value)
    from_best = d["groups"][str(best)]["fused_cells_from_it"]
    assert from_best > 0.3
    sig = [v["noise_m"] for v in d["groups"].values()]
    tol = 2.5 * np.sqrt(2) * max(sig) + 1e-4
    with np.errstate(invalid="ignore"):
        near = np.abs(H - Hb) <= tol
    assert near.sum() >= np.floor(from_best * H.size)
    assert np.sum(H == Hb) >= 0.2 * np.floor(from_best * H.size)     # where only it saw the ground
    assert np.isfinite(H).mean() > np.isfinite(Hb).mean()  # and the others fill its holes
    ev = rep["eval"]
    assert set(ev["groups"]) == {"0", "1"}
    best_alone = ev["groups"][str(best)]["aligned"]
    assert ev["aligned"]["completeness_pct"] > best_alone["completeness_pct"]
    # the noise model: each group's geometry from its upgraded views, one matching precision
    nm = d["noise_model"]
    geo = {g: v["geometry_m_per_px"] for g, v in d["groups"].items()}
    assert all(0 < a < 50 for a in geo.values()) and 0 < nm["matching_precision_px"] < 3
    for g, v in d["groups"].items():
        assert v["noise_m"] == pytest.approx(nm["matching_precision_px"] * geo[g])
    # the fused DSM against each group on the cells both cover, also in eval.json (the viewer)
    on_file = json.loads((lay.eval_dir / "eval.json").read_text())
    for g in ("0", "1"):
        sc = ev["groups"][g]["fused_vs_group_same_cells"]
        assert sc["cells"] > 0 and sc["a"]["median_abs_err_m"] is not None
        assert on_file["groups"][g]["fused_vs_group_same_cells"] == sc
    # the agreement layer: on dsm.tif's grid, a count where it has a height (0, 1 or 2 groups),
    # its shares in the report, and the DSM scored by count in the evaluation (and eval.json)
    A, grid_a = read_dsm(lay.dsm_agreement)
    assert grid_a == grid
    np.testing.assert_array_equal(np.isnan(A), np.isnan(H))
    assert set(np.unique(A[np.isfinite(A)]).tolist()) <= {0.0, 1.0, 2.0} and np.any(A == 2)
    frac = d["agreement"]["fraction_of_valid_cells"]
    for k, f in frac.items():
        assert f == pytest.approx(np.mean(A[np.isfinite(A)] == float(k)))
    ba = ev["by_agreement"]["classes"]
    assert set(ba) <= {"0", "1", "2"} and "2" in ba and on_file["by_agreement"] == ev["by_agreement"]
    assert sum(v["completeness_share_pct"] for v in ba.values()) == pytest.approx(
        ev["aligned"]["completeness_pct"], abs=1.0)


def test_the_icp_reference_is_the_largest_full_cloud_not_the_largest_sample(tmp_path):
    """make_dsm samples clouds for ICP; the reference must still be the group with the most
    points (a regression: 210 points give 70 samples, 200 points give 100)."""
    from types import SimpleNamespace

    from recon_core.config import Config
    from recon_core.euclidean.dsm_stage import make_dsm
    from recon_core.geometry.geodesy import LocalFrame
    from recon_core.io.models import PointSource

    rng = np.random.default_rng(0)

    def cloud(n):
        xy = rng.uniform(-50, 50, (n, 2))
        return np.column_stack([xy, 0.1 * xy[:, 0] + rng.normal(0, 0.05, n)])

    sources = {0: PointSource(cloud(210), np.full(210, 100, np.uint8)),
               1: PointSource(cloud(200), np.full(200, 100, np.uint8))}
    cfg = Config().with_overrides({"dsm.icp_sample_points": 100})
    site = SimpleNamespace(hints={}, root=tmp_path)
    rep = make_dsm(site, sources, {0: np.eye(4), 1: np.eye(4)}, LocalFrame(30.0, 31.2, 0.0), 0.5, cfg,
                   OutLayout(tmp_path))
    assert rep["fusion"]["reference_group"] == 0
    assert (tmp_path / "dsm.tif").exists() and OutLayout(tmp_path).group_dsms() == [0, 1]


def test_a_bent_lower_group_is_brought_onto_the_best_before_it_fills_holes():
    """The best group: the true surface with holes (30 % of the cells, in patches). A worse
    group: complete, but bent by a smooth 2 m dome and offset. Filling the holes with it as is
    leaves the bend in them; with the relative correction the filled cells follow the truth
    (and a group that agrees with the best is left as it is)."""
    rng = np.random.default_rng(4)
    h, w = 400, 500
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    truth = 100 + 0.01 * xx + 3 * ((xx // 40 + yy // 40) % 2)         # blocks of "buildings"
    best = truth + rng.normal(0, 0.1, truth.shape).astype(np.float32)
    holes = np.zeros((h, w), bool)
    for _ in range(40):
        r, c = rng.integers(0, h - 30), rng.integers(0, w - 30)
        holes[r:r + int(rng.integers(10, 30)), c:c + int(rng.integers(10, 30))] = True
    best[holes] = np.nan
    bend = 2.0 * (((xx - w / 2) / (w / 2)) ** 2 + ((yy - h / 2) / (h / 2)) ** 2) - 1.0 + 0.7
    worse = truth + bend + rng.normal(0, 0.1, truth.shape).astype(np.float32)
    plain, src = fuse_groups([best.astype(np.float32), worse.astype(np.float32)])
    fixed, _ = fuse_groups([best.astype(np.float32), worse.astype(np.float32)], correct_block=32)
    filled = (src == 1)
    assert filled.sum() > 0.05 * h * w
    err_plain = np.median(np.abs(plain[filled] - truth[filled]))
    err_fixed = np.median(np.abs(fixed[filled] - truth[filled]))
    assert err_plain > 0.6 and err_fixed < 0.2, (err_plain, err_fixed)
    # cells of the best group are never changed
    assert np.array_equal(fixed[~holes], best[~holes])
    # a lower group that agrees with the best is left (nearly) as it is
    agree = truth + rng.normal(0, 0.1, truth.shape).astype(np.float32)
    same, _ = fuse_groups([best.astype(np.float32), agree.astype(np.float32)], correct_block=32)
    assert np.median(np.abs(same[filled] - agree[filled])) < 0.05


def test_groups_that_agree_are_averaged_and_one_that_disagrees_is_left_out():
    """Three matchings of the same ground (noise 0.1, 0.2, 0.2 m); the third also has a patch
    2 m off (a shadow, a moved car). Fused with the noise of each, the common cells are more
    accurate than the best group alone, the patch keeps the others' value, and holes of the
    best are still filled."""
    rng = np.random.default_rng(4)
    h, w = 200, 240
    truth = rng.uniform(0, 20, (h, w)).astype(np.float32)
    sig = [0.1, 0.2, 0.2]
    D = [(truth + rng.normal(0, s, truth.shape)).astype(np.float32) for s in sig]
    D[2][50:90, 60:120] += 2.0
    D[0][150:190, 10:60] = np.nan
    plain, _ = fuse_groups(D)
    avg, src = fuse_groups(D, sigmas=sig)
    common = np.isfinite(D[0])
    e_best = np.median(np.abs(D[0][common] - truth[common]))
    e_avg = np.median(np.abs(avg[common] - truth[common]))
    assert np.array_equal(plain[common], D[0][common])
    assert e_avg < 0.85 * e_best, (e_avg, e_best)
    patch = np.s_[50:90, 60:120]
    assert np.median(np.abs(avg[patch] - truth[patch])) < e_best      # the +2 m group left out
    hole = np.s_[150:190, 10:60]
    assert np.all(src[hole] == 1) and np.median(np.abs(avg[hole] - truth[hole])) < 0.2
    # a DSM without a noise figure only fills; averaging off gives the plain rule
    assert np.array_equal(fuse_groups(D, sigmas=[0.1, None, None])[0], plain)
    assert np.array_equal(fuse_groups(D, sigmas=sig, agree_sigmas=0)[0], plain)


def test_fusion_by_strips_on_disk_equals_one_strip(tmp_path):
    """Fusing by strips of rows from disk-backed DSMs (and masked views of them) into
    disk-backed outputs gives exactly the DSM and sources of one strip in memory, for even and
    odd correction blocks and a grid narrower than one block: the smooth correction is the same
    up-sampled surface, the averaging the same per cell."""
    from recon_core.euclidean.dsm_stage import RowView, count_rows, group_noise

    rng = np.random.default_rng(6)
    h, w = 333, 290
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    truth = 100 + 0.01 * xx + 3 * ((xx // 40 + yy // 40) % 2)
    D = []
    for k, s in enumerate((0.1, 0.2, 0.3)):
        d = (truth + k * 0.3 * np.sin(yy / 90.0) + rng.normal(0, s, truth.shape)).astype(np.float32)
        for _ in range(30):
            r, c = rng.integers(0, h - 20), rng.integers(0, w - 20)
            d[r:r + int(rng.integers(3, 20)), c:c + int(rng.integers(3, 20))] = np.nan
        D.append(d)
    for block, cols in ((13, slice(None)), (49, slice(0, 30))):    # odd blocks; a narrow grid
        narrow = [np.ascontiguousarray(d[:, cols]) for d in D]
        one = fuse_groups(narrow, correct_block=block, sigmas=[0.1, 0.2, 0.3], min_overlap=200,
                          block_rows=10_000)
        for rows in (1, 50, 98):
            H3, s3 = fuse_groups(narrow, correct_block=block, sigmas=[0.1, 0.2, 0.3],
                                 min_overlap=200, block_rows=rows)
            assert np.array_equal(H3, one[0], equal_nan=True) and np.array_equal(s3, one[1]), (block, rows)
    kw = dict(correct_block=16, sigmas=[0.1, 0.2, 0.3], min_overlap=500)
    H1, s1 = fuse_groups(D, block_rows=10_000, **kw)
    disk = []
    for k, d in enumerate(D):
        m = np.lib.format.open_memmap(tmp_path / f"d{k}.npy", "w+", np.float32, d.shape)
        m[:] = d
        disk.append(m)
    views = [disk[0]] + [RowView(d.shape, (lambda m: lambda a, b: np.asarray(m[a:b]))(m)) for m in disk[1:]]
    out = np.lib.format.open_memmap(tmp_path / "H.npy", "w+", np.float32, (h, w))
    src = np.lib.format.open_memmap(tmp_path / "s.npy", "w+", np.int16, (h, w))
    for rows in (16, 40, 100):
        H2, s2 = fuse_groups(views, block_rows=rows, out=out, source_out=src, **kw)
        assert H2 is out and np.array_equal(np.asarray(H2), H1, equal_nan=True), rows
        assert np.array_equal(np.asarray(s2), s1), rows
    assert (s1 == 2).sum() > 0 and count_rows(src, lambda v: v == 1, block_rows=7) == int((s1 == 1).sum())
    # a strided view reads the same cells as the array
    assert np.array_equal(views[1][::3, ::2], D[1][::3, ::2], equal_nan=True)
    assert group_noise(dict(enumerate(views)), 16, max_cells=20_000) == \
        group_noise(dict(enumerate(D)), 16, max_cells=20_000)


def test_the_euclidean_cloud_is_also_a_laz_with_its_crs(tiny2_run):
    """cloud.laz holds cloud.ply's points to the millimetre, in the DSM's CRS, heights said to
    be ellipsoidal (what PDAL and QGIS read: the WKT VLR)."""
    import laspy

    from recon_core.io.ply import read_ply

    lay = tiny2_run.layout
    las = laspy.read(lay.cloud_laz)
    xyz, rgb, _ = read_ply(lay.cloud)
    epsg = json.loads(lay.report.read_text())["stages"]["dsm"]["crs_epsg"]
    assert las.header.parse_crs().to_epsg() == epsg
    assert las.header.point_count == len(xyz)
    got = np.column_stack([las.x, las.y, las.z])
    assert np.abs(got - xyz).max() <= 0.0006
    np.testing.assert_array_equal(np.asarray(las.red) // 257, rgb[:, 0])
    assert any(b"ellipsoid" in v.record_data for v in las.header.vlrs if v.user_id == "AE-Rec")


def test_groups_reconstructed_apart_are_fused_by_icp(tmp_path):
    """With sfm.joint_groups off (as the paper does, or when the dates do not match), each group
    has its own frame and its own H_A, and ICP brings the others onto the reference."""
    from recon_core.config import Config
    from recon_core.pipeline import run
    from recon_core.synthetic.generator import generate_site

    generate_site(tmp_path / "site", preset="tiny2", seed=0)
    cfg = Config()
    cfg.sfm.joint_groups = False
    state = run(tmp_path / "site", tmp_path / "out", cfg, resume=False)
    assert all("joint" not in m.stats for m in state.models.values())
    maps, _ = state.upgrade
    assert not np.allclose(maps[0].H, maps[1].H)
    fusion = json.loads(state.layout.report.read_text())["stages"]["dsm"]["fusion"]
    other = str(1 - fusion["reference_group"])
    assert "joint" not in fusion and fusion["icp"][other]["fitness"] > 0.3


def test_grid_files_are_allocated_up_front(tmp_path):
    """A memory-mapped grid's file gets its disk blocks when it is made (a full disk is then an
    error there, not a crash at the first write of a page)."""
    import os

    from recon_core.euclidean.dsm_stage import reserve_disk

    p = tmp_path / "g.npy"
    np.lib.format.open_memmap(p, mode="w+", dtype=np.float32, shape=(2000, 1500))
    size = os.stat(p).st_size
    assert os.stat(p).st_blocks * 512 < size / 2          # numpy leaves it sparse
    reserve_disk(p)
    assert os.stat(p).st_blocks * 512 >= size


def test_the_correction_surface_is_the_same_strip_by_strip():
    """The up-sampled correction of any strip equals that strip of the whole surface, bit for
    bit, for odd and even blocks and tall grids (each value from its row and column in the
    whole grid), and it is bilinear up-sampling with cell centres aligned (cv2.resize's)."""
    import cv2

    from recon_core.euclidean.dsm_stage import correction_rows

    rng = np.random.default_rng(2)
    for block, nb_r, nb_c in ((49, 123, 3), (107, 40, 2), (64, 30, 4), (13, 300, 1)):
        coarse = rng.normal(0, 1, (nb_r, nb_c)).astype(np.float32)
        h, w = nb_r * block - 7, nb_c * block - 3
        whole = correction_rows(coarse, block, 0, h, w)
        step = 1024 // block * block
        strips = np.vstack([correction_rows(coarse, block, r0, min(h, r0 + step), w)
                            for r0 in range(0, h, step)])
        assert np.array_equal(strips, whole), block
        ref = cv2.resize(coarse, (nb_c * block, nb_r * block), interpolation=cv2.INTER_LINEAR)
        assert np.abs(whole - ref[:h, :w]).max() < 1e-4      # cv2 weights in float32


def test_fill_agreeing_keeps_only_the_holes_two_groups_agree_on():
    """The best group has holes; two worse groups fill them. Where only one worse group sees a
    hole (and it is often wrong there, as at occlusions), fill_agreeing=2 leaves it empty;
    where both see it and agree, the hole is filled; the best group's own cells do not change,
    and fill_agreeing=1 fills everything as before."""
    rng = np.random.default_rng(5)
    h, w = 200, 240
    truth = np.zeros((h, w), np.float32)
    best = truth + rng.normal(0, 0.1, truth.shape).astype(np.float32)
    best[:, :120] = np.nan                                   # the left half: a hole
    g1 = truth + rng.normal(0, 0.2, truth.shape).astype(np.float32)
    g2 = truth + rng.normal(0, 0.2, truth.shape).astype(np.float32)
    g2[:100] = np.nan                                        # only g1 sees the top-left quarter
    g1[:100, :120] += rng.choice([-3.0, 3.0], (100, 120)).astype(np.float32)   # and it is wrong
    sig = [0.1, 0.2, 0.2]
    any_fill, _ = fuse_groups([best, g1, g2], sigmas=sig)
    agreed, src = fuse_groups([best, g1, g2], sigmas=sig, fill_agreeing=2)
    assert np.isfinite(any_fill[:100, :120]).all()
    assert np.isnan(agreed[:100, :120]).all() and (src[:100, :120] == -1).all()
    bottom = agreed[100:, :120]
    assert np.isfinite(bottom).mean() > 0.95 and np.nanmedian(np.abs(bottom)) < 0.15
    np.testing.assert_array_equal(agreed[:, 120:], any_fill[:, 120:])
    # the agreement layer says which cells to trust: in the bottom right all three agree (all but
    # the rare noise outliers), in the top right and the bottom left two, in the top left only the
    # wrong one; NaN where the fused DSM has no height; a noiseless fill counts 0
    agree = np.empty((h, w), np.float32)
    fuse_groups([best, g1, g2], sigmas=sig, agree_out=agree)
    assert np.mean(agree[100:, 120:] == 3) > 0.95
    assert np.mean(agree[:100, 120:] == 2) > 0.95 and np.mean(agree[100:, :120] == 2) > 0.95
    assert np.all(agree[:100, :120] == 1)
    np.testing.assert_array_equal(np.isnan(agree), np.isnan(any_fill))
    fuse_groups([best, g1, g2], sigmas=sig, fill_agreeing=2, agree_out=agree)
    np.testing.assert_array_equal(np.isnan(agree), np.isnan(agreed))
    weak = np.where(np.isnan(g1) | np.isnan(best), truth, np.nan)     # a weak pair's cells: no noise
    g1[:100, :120] = np.nan
    fuse_groups([best, g1, g2, weak], sigmas=sig + [None], agree_out=agree)
    assert np.all(agree[:100, :120] == 0)
    # without an agreement test there are no counts
    fuse_groups([best, g1, g2], sigmas=sig, agree_sigmas=0, agree_out=agree)
    assert np.isnan(agree).all()


def test_fill_agreeing_without_an_agreement_test_is_refused():
    """fusion_fill_agreeing counts agreeing groups: with fusion_agree_sigmas = 0 there is no
    agreement to count, and the configuration is refused before any compute."""
    from recon_core.config import Config
    from recon_core.errors import InputError
    from recon_core.preflight import check_config

    check_config(Config().with_overrides({"dsm.fusion_fill_agreeing": 2}))
    with pytest.raises(InputError, match="fusion_agree_sigmas"):
        check_config(Config().with_overrides({"dsm.fusion_fill_agreeing": 2, "dsm.fusion_agree_sigmas": 0.0}))
    with pytest.raises(InputError, match="fusion_fill_agreeing"):
        check_config(Config().with_overrides({"dsm.fusion_fill_agreeing": 0}))
