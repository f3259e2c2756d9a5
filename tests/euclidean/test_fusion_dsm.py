"""Fusing date groups into one DSM: the best-checked group wins each cell it sees, the others
fill its holes; each group's own DSM and scores are kept."""

from __future__ import annotations

import json

import numpy as np
import pytest

from recon_core.euclidean.dsm_stage import fuse_groups, group_quality, rank_groups
from recon_core.io.layout import OutLayout
from recon_core.io.raster import read_dsm


def test_rank_and_fuse():
    assert rank_groups([0, 1, 2], {0: 0.8, 2: 0.3}, {0: 10, 1: 99, 2: 5}) == [2, 0, 1]
    assert rank_groups([0, 1], {}, {0: 10, 1: 99}) == [1, 0]
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
    from recon_core.pipeline import run
    from recon_core.synthetic.generator import generate_site

    root = tmp_path_factory.mktemp("tiny2")
    generate_site(root / "site", preset="tiny2", seed=0)
    return run(root / "site", root / "out", resume=False)


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
    # every cell the best group saw is its own value in the fused DSM (hole filling, done on
    # each DSM separately, only touches cells without a value)
    from_best = d["groups"][str(best)]["fused_cells_from_it"]
    assert from_best > 0.3 and np.sum(H == Hb) >= np.floor(from_best * H.size)
    assert np.isfinite(H).mean() > np.isfinite(Hb).mean()  # and the others fill its holes
    ev = rep["eval"]
    assert set(ev["groups"]) == {"0", "1"}
    best_alone = ev["groups"][str(best)]["aligned"]
    assert ev["aligned"]["completeness_pct"] > best_alone["completeness_pct"]


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
