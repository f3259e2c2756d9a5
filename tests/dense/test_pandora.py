"""The `pandora` matcher (CNES pandora + pandora_plugin_libsgm, an optional extra) on rectified
pairs made by warping a texture with a known disparity field, against that field; its sign
convention against SGBM's; and its refusal, in one line before any compute, where pandora is not
installed. Tests that match skip when pandora is absent."""

from __future__ import annotations

import pickle
import sys

import numpy as np
import pytest

from recon_core.cli import main
from recon_core.config import Config, PandoraConfig
from recon_core.dense.matchers import MATCHERS, PandoraMatcher, SgbmMatcher, make_matcher, pandora_pipeline
from tests.dense.pairs import block_pair, smooth_pair


def _need_pandora():
    pytest.importorskip("pandora")
    pytest.importorskip("pandora_plugin_libsgm")


def test_pandora_recovers_a_slanted_plane_to_a_fraction_of_a_pixel():
    """d = 2.3 + 0.02 u - 0.01 v: every sub-pixel phase present; the interior is matched and
    within 0.15 px (median; 0.06 px measured, SGBM 0.12 px) of the truth; same sign as SGBM."""
    _need_pandora()
    left, right, d_true = smooth_pair(lambda u, v: 2.3 + 0.02 * u - 0.01 * v)
    d, valid = PandoraMatcher().match(left, right, -2.0, 9.0)
    assert d.shape == left.shape and d.dtype == np.float32 and valid.dtype == bool
    assert np.array_equal(valid, np.isfinite(d))
    inner = (slice(8, -8), slice(20, -20))
    err = np.abs(d - d_true)[inner]
    assert valid[inner].mean() > 0.9
    assert np.nanmedian(err) < 0.15 and np.nanpercentile(err, 90) < 0.35
    ds, vs = SgbmMatcher().match(left, right, -2.0, 9.0)
    both = valid & vs
    assert np.nanmedian((d - ds)[both]) == pytest.approx(0.0, abs=0.3)       # one convention


def test_pandora_recovers_a_step_and_invalidates_what_it_cannot_see():
    """A 'building': d = 1 on the ground, 7 on a 50 x 60 px block. Away from its edges (4 px) both
    levels are found within 0.15 px (0.04 px measured); the ground the block hides in the right image (the 6 px strip
    right of it) is mostly left invalid rather than given a wrong value."""
    _need_pandora()
    left, right, d_true, block, ground, hidden = block_pair()
    d, valid = PandoraMatcher().match(left, right, -4.0, 12.0)
    for zone in (block, ground):
        assert valid[zone].mean() > 0.9
        assert np.nanmedian(np.abs(d - d_true)[zone]) < 0.15
    wrong = valid[hidden] & (np.abs(d - d_true)[hidden] > 1.0)
    assert wrong.mean() < 0.2


def test_pandora_matcher_is_picklable_and_chosen_by_name():
    cfg = Config().with_overrides({"dense.matcher": "pandora", "pandora.census_window": 7})
    m = make_matcher(cfg)
    assert isinstance(m, PandoraMatcher) and m.cfg.census_window == 7
    assert pickle.loads(pickle.dumps(m)) == m
    assert set(MATCHERS) == {"sgbm", "mgm", "pandora"}
    assert m.margin_px >= 7 // 2
    pipe = pandora_pipeline(PandoraConfig(median_size=1))["pipeline"]
    assert "filter" not in pipe and pipe["validation"]["validation_method"] == "cross_checking_accurate"


def _match_in_worker(job):
    matcher, left, right = job
    d, valid = matcher.match(left, right, -2.0, 9.0)
    return float(np.nanmedian(d)), float(valid.mean())


def test_pandora_matches_in_a_worker_process():
    """Jobs carry the matcher to forkserver workers: pandora is imported and run there."""
    _need_pandora()
    from recon_core.dense.executor import make_executor

    left, right, d_true = smooth_pair(lambda u, v: 3.4 + 0.0 * u, 80, 140)
    with make_executor(None, 1) as ex:
        (med, frac), = list(ex.map_unordered(_match_in_worker, [(PandoraMatcher(), left, right)]))
    assert med == pytest.approx(3.4, abs=0.25) and frac > 0.7


class _NoPandora:
    """A meta-path finder that makes pandora look uninstalled."""

    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in ("pandora", "pandora_plugin_libsgm"):
            raise ModuleNotFoundError(f"No module named {name!r}")
        return None


def test_choosing_pandora_without_it_is_refused_in_one_line(small_site, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(sys, "meta_path", [_NoPandora(), *sys.meta_path])
    for mod in [m for m in sys.modules if m.split(".")[0] in ("pandora", "pandora_plugin_libsgm")]:
        monkeypatch.delitem(sys.modules, mod)
    f = tmp_path / "c.toml"
    f.write_text('[dense]\nmatcher = "pandora"\n')
    out = tmp_path / "o"
    assert main(["run", str(small_site), "--out", str(out), "--config", str(f), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "dense.matcher = 'pandora'" in err[0] and "pip install 'aerec[pandora]'" in err[0], err
    assert not out.exists()


def test_pandora_penalties_are_checked_like_sgbm_s(small_site, tmp_path, capsys):
    f = tmp_path / "c.toml"
    f.write_text("[pandora]\np1 = 40\np2 = 10\n")
    assert main(["run", str(small_site), "--out", str(tmp_path / "o"), "--config", str(f), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("aerec: error:") == 1 and "P2 must be > P1" in err, err


def test_the_dense_stage_depends_on_its_own_matcher_s_section(small_site):
    """A run resumed with other pandora parameters redoes its dense stage; an SGBM run's hashes
    do not move with the pandora section (runs made before it existed keep theirs)."""
    from recon_core.io.site import load_site
    from recon_core.resume import stage_hash

    site = load_site(small_site)
    sg = Config()
    assert stage_hash(sg, "dense", site) == stage_hash(sg.with_overrides({"pandora.p1": 9.0}), "dense", site)
    pa = Config().with_overrides({"dense.matcher": "pandora"})
    assert stage_hash(pa, "sparse", site) == stage_hash(sg, "sparse", site)
    assert stage_hash(pa, "dense", site) != stage_hash(sg, "dense", site)
    assert stage_hash(pa, "dense", site) != stage_hash(pa.with_overrides({"pandora.p1": 9.0}), "dense", site)


def test_the_extra_brings_what_the_matcher_imports():
    """pyproject.toml's `pandora` extra lists a distribution for each package the check looks
    for, each bounded below its next major release."""
    import re
    import tomllib
    from pathlib import Path

    from recon_core.extras import EXTRAS

    deps = tomllib.loads((Path(__file__).resolve().parents[2] / "pyproject.toml").read_text())[
        "project"]["optional-dependencies"]["pandora"]
    names = {re.split(r"[<>=!~ ]", d)[0].replace("-", "_").lower(): d for d in deps}
    assert set(names) == set(EXTRAS["pandora"])
    assert all("<" in d for d in deps)


def test_a_run_that_stops_before_the_dense_stage_needs_no_extra(tiny_site, tmp_path, monkeypatch):
    """dense.matcher = "pandora" without pandora: a run with --stage sparse is not refused (it
    never matches), nor is reading the file alone."""
    monkeypatch.setattr(sys, "meta_path", [_NoPandora(), *sys.meta_path])
    for mod in [m for m in sys.modules if m.split(".")[0] in ("pandora", "pandora_plugin_libsgm")]:
        monkeypatch.delitem(sys.modules, mod)
    from recon_core.config import config_from_toml

    f = tmp_path / "c.toml"
    f.write_text('[dense]\nmatcher = "pandora"\n')
    assert config_from_toml(f).dense.matcher == "pandora"
    out = tmp_path / "o"
    assert main(["run", str(tiny_site), "--out", str(out), "--config", str(f), "--stage", "sparse",
                 "--preset", "tiny", "--quiet"]) == 0
    assert (out / "stages" / "sparse.json").exists()
