"""The built-in `mgm` matcher (recon_core.dense.mgm) on rectified pairs with a known disparity
field, against that field; what makes it MGM and not SGM (each message from two neighbours);
its row strips (a memory budget) against one whole volume; and a run that uses it."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from recon_core.config import Config
from recon_core.dense import mgm
from recon_core.dense.matchers import MgmMatcher, SgbmMatcher, make_matcher
from tests.dense.pairs import block_pair, smooth_pair


def test_mgm_recovers_a_slanted_plane_to_a_fraction_of_a_pixel():
    """d = 2.3 + 0.02 u - 0.01 v: every sub-pixel phase present; the interior matched and within
    0.15 px (median) of the truth; the same sign convention as SGBM."""
    left, right, d_true = smooth_pair(lambda u, v: 2.3 + 0.02 * u - 0.01 * v)
    d, valid = MgmMatcher().match(left, right, -2.0, 9.0)
    assert d.shape == left.shape and d.dtype == np.float32 and np.array_equal(valid, np.isfinite(d))
    inner = (slice(8, -8), slice(20, -20))
    err = np.abs(d - d_true)[inner]
    assert valid[inner].mean() > 0.9
    assert np.nanmedian(err) < 0.15 and np.nanpercentile(err, 90) < 0.35, np.nanmedian(err)
    ds, vs = SgbmMatcher().match(left, right, -2.0, 9.0)
    assert np.nanmedian((d - ds)[valid & vs]) == pytest.approx(0.0, abs=0.3)


def test_mgm_recovers_a_step_and_invalidates_what_it_cannot_see():
    """A block 6 px above the ground: both levels found within 0.15 px away from the edges; the
    ground the block hides in the right image mostly left invalid, not given a wrong value."""
    left, right, d_true, block, ground, hidden = block_pair()
    d, valid = MgmMatcher().match(left, right, -4.0, 12.0)
    for zone in (block, ground):
        assert valid[zone].mean() > 0.9
        assert np.nanmedian(np.abs(d - d_true)[zone]) < 0.15
    wrong = valid[hidden] & (np.abs(d - d_true)[hidden] > 1.0)
    assert wrong.mean() < 0.2


def test_each_message_comes_from_two_neighbours():
    """MGM's recursion on a 3 x 3 x 2 volume, by hand: the pass from the left and from above at
    the centre averages the messages of (1, 0) and (0, 1); SGM's would take only (1, 0)."""
    C = np.zeros((3, 3, 2), np.float32)
    C[:, :, 1] = 5.0                          # every pixel prefers d = 0 ...
    C[0, 1] = (9.0, 0.0)                      # ... but the one above the centre prefers d = 1
    S = np.zeros_like(C)
    L = np.empty_like(C)
    (a, b, col_major, ys, xs) = mgm._SWEEPS[0]
    mgm._sweep(C, S, L, *a, *b, col_major, ys, xs, np.float32(1.0), np.float32(100.0))
    # above the centre: its own cost + the average of its left (0, 0) message only
    # (0, 0) has L = C = (0, 5); message to (0, 1): min(L, L -+ 1 + P1) - min = (0, 1)
    assert L[0, 1].tolist() == pytest.approx([9.0 + 0.0, 0.0 + 1.0])
    # the centre: left neighbour (1, 0) and upper (0, 1), each normalised, averaged
    left_msg = L[1, 0] - L[1, 0].min()
    left_msg = np.minimum(left_msg, left_msg[::-1] + 1.0)
    up = L[0, 1] - L[0, 1].min()
    up = np.minimum(up, up[::-1] + 1.0)
    assert L[1, 1] == pytest.approx(C[1, 1] + 0.5 * (left_msg + up))
    assert np.array_equal(S, L)


def test_row_strips_match_one_whole_volume(monkeypatch):
    """A memory budget that forces several strips changes the disparities only where a strip's
    seam cuts the messages short: almost nowhere, and by little."""
    left, right, _ = smooth_pair(lambda u, v: 2.3 + 0.004 * u - 0.01 * v, h=240, w=900)
    whole = mgm.mgm_disparity(left, right, -2.0, 9.0, max_volume_mb=512)
    volumes = []
    real = mgm.cost_volume
    monkeypatch.setattr(mgm, "cost_volume", lambda cl, *a: volumes.append(cl.shape) or real(cl, *a))
    parts = mgm.mgm_disparity(left, right, -2.0, 9.0, max_volume_mb=16, overlap_rows=32)
    assert len(volumes) > 2 and max(h * w * 14 * 4 * 3 for h, w in volumes) <= 16 * 2 ** 20
    volumes.clear()          # context rows that would not fit the budget are fewer, not over it
    mgm.mgm_disparity(left, right, -2.0, 9.0, max_volume_mb=16, overlap_rows=200)
    assert len(volumes) > 2 and max(h * w * 14 * 4 * 3 for h, w in volumes) <= 16 * 2 ** 20
    both = np.isfinite(whole) & np.isfinite(parts)
    assert both.mean() > 0.9
    assert np.mean(np.abs(whole - parts)[both] > 0.05) < 0.01


def test_strips_cover_every_row_once():
    for h, rows, ov in ((100, 200, 10), (1000, 100, 32), (1001, 100, 0), (257, 16, 64)):
        s = mgm.strips(h, rows, ov)
        kept = np.concatenate([np.arange(k0, k1) for _, _, k0, k1 in s])
        assert np.array_equal(kept, np.arange(h))
        for a, b, k0, k1 in s:
            assert a <= k0 < k1 <= b and b - a <= rows + 2 * ov


def test_mgm_is_chosen_by_name_and_picklable():
    cfg = Config().with_overrides({"dense.matcher": "mgm", "mgm.census_window": 7})
    m = make_matcher(cfg)
    assert isinstance(m, MgmMatcher) and m.cfg.census_window == 7
    assert pickle.loads(pickle.dumps(m)) == m
    assert m.margin_px >= 7 // 2


def test_the_default_mgm_run_is_as_accurate_as_sgbm(tiny_run, tmp_path):
    """`tiny` (defaults: MGM) reconstructed again from the same sparse stage with dense.matcher =
    "sgbm": MGM's DSM against the generator's truth is about as accurate and complete."""
    import shutil

    from recon_core.config import preset
    from recon_core.pipeline import run

    state, _ = tiny_run
    assert state.cfg.dense.matcher == "mgm"
    out = tmp_path / "o"
    shutil.copytree(state.out, out)
    again = run(state.site.root, out, preset("tiny").with_overrides({"dense.matcher": "sgbm"}))
    assert again.report["stages"]["dense"] != state.report["stages"]["dense"]   # matched again
    mg, sg = state.report["stages"]["eval"]["aligned"], again.report["stages"]["eval"]["aligned"]
    # measured: ME 0.386 m against 0.386, CP 71.6 % against 70.5, coverage 88.9 % against 86.8
    assert mg["median_abs_err_m"] <= sg["median_abs_err_m"] + 0.03, (mg, sg)
    assert mg["completeness_pct"] >= sg["completeness_pct"] - 1.0, (mg, sg)
