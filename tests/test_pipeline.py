"""The whole pipeline: outputs, report, resume, and the real Pleiades pair (when present)."""

from __future__ import annotations

import json

import numpy as np
import rasterio

from recon_core.cli import main
from recon_core.config import preset
from recon_core.events import EventBus, Message
from recon_core.pipeline import STAGES, run


def test_tiny_outputs_and_report(tiny_run):
    state, _ = tiny_run
    out = state.out
    rep = json.loads((out / "report.json").read_text())
    assert set(STAGES) <= set(rep["stages"])
    for f in ("dsm.tif", "cloud.ply", "affine/group_0/cameras.json", "affine/group_0/sparse.ply",
              "affine/group_0/dense.ply", "upgrade/group_0.json", "eval/height_error.png"):
        assert (out / f).exists(), f
    with rasterio.open(out / "dsm.tif") as ds:
        assert ds.crs.to_epsg() == state.site.hints["crs_epsg"]
        assert ds.dtypes[0] == "float32" and np.isnan(ds.nodata)
    up = rep["stages"]["upgrade"]["groups"]["0"]
    assert up["stats"]["check"]["n"] >= 3
    ev = rep["stages"]["eval"]
    assert {"aligned", "unaligned", "alignment"} <= set(ev)


def test_resume_reloads_finished_stages(tiny_run):
    state, _ = tiny_run
    msgs: list = []
    state2 = run(state.site.root, state.out, preset("tiny"), bus=EventBus(msgs.append))
    reloaded = [m.text for m in msgs if isinstance(m, Message) and "already done" in m.text]
    assert len(reloaded) == len(STAGES)
    np.testing.assert_allclose(state2.models[0].cams, state.models[0].cams)


def test_changed_gcps_redo_only_from_upgrade(tiny_run, tmp_path):
    import shutil

    state, _ = tiny_run
    site = tmp_path / "site"
    shutil.copytree(state.site.root, site)
    out = tmp_path / "out"
    shutil.copytree(state.out, out)
    doc = json.loads((site / "gcps.geojson").read_text())
    doc["features"] = doc["features"][:-1]                    # one GCP fewer
    (site / "gcps.geojson").write_text(json.dumps(doc))
    msgs: list = []
    run(site, out, preset("tiny"), bus=EventBus(msgs.append))
    reloaded = {m.text.split(":")[0] for m in msgs if isinstance(m, Message) and "already done" in m.text}
    assert reloaded == {"sparse", "dense"}


def test_real_gizeh_pair_end_to_end(shared_data, tmp_path, capsys):
    """The smallest real site: 4 control GCPs, 8 check points; RPCs are never read."""
    site = shared_data / "gizeh_pair"
    out = tmp_path / "gizeh"
    assert main(["run", str(site), "--out", str(out), "--quiet"]) == 0
    rep = json.loads((out / "report.json").read_text())
    up = rep["stages"]["upgrade"]["groups"]["0"]
    assert up["n_control_used"] == 4
    chk = up["stats"]["check"]
    assert chk["n"] == 8
    assert chk["rmse_horizontal_m"] < 0.5 and chk["rmse_U_m"] < 1.0
    assert main(["eval", str(out / "dsm.tif"), str(site / "ref_dsm_s2p.tif"), "--out", str(tmp_path / "ev")]) == 0
    ev = json.loads((tmp_path / "ev" / "eval.json").read_text())
    assert ev["aligned"]["median_abs_err_m"] < 2.0         # agreement with s2p, not accuracy


def test_run_without_gcps_keeps_affine_outputs(tiny_run, tmp_path, capsys):
    import shutil

    state, _ = tiny_run
    site = tmp_path / "site"
    shutil.copytree(state.site.root, site)
    (site / "gcps.geojson").unlink()
    out = tmp_path / "out"
    shutil.copytree(state.out, out)
    code = main(["run", str(site), "--out", str(out), "--preset", "tiny", "--quiet", "--stage", "upgrade"])
    err = capsys.readouterr().err
    assert code == 2 and "no GCP" in err and "Traceback" not in err
    assert (out / "affine" / "group_0" / "dense.ply").exists()


def test_out_gcp_file_wins_and_redoes_upgrade(tiny_run, tmp_path):
    """The viewer's working set OUT/gcps.geojson feeds the upgrade (and its stage hash)."""
    import shutil

    state, _ = tiny_run
    out = tmp_path / "out"
    shutil.copytree(state.out, out)
    doc = json.loads((state.site.root / "gcps.geojson").read_text())
    doc["features"] = doc["features"][:-2]
    (out / "gcps.geojson").write_text(json.dumps(doc))
    msgs: list = []
    run(state.site.root, out, preset("tiny"), bus=EventBus(msgs.append))
    texts = [m.text for m in msgs if isinstance(m, Message)]
    assert any("viewer's working set" in t for t in texts)
    reloaded = {t.split(":")[0] for t in texts if "already done" in t}
    assert reloaded == {"sparse", "dense"}
    rep = json.loads((out / "report.json").read_text())
    assert rep["gcp_file"].endswith("out/gcps.geojson")
    n_pts = len(rep["stages"]["upgrade"]["groups"]["0"]["points"])
    assert n_pts == len(doc["features"])


def test_dsm_by_small_chunks_and_spilled_blocks_is_identical(tiny_run, tmp_path):
    """The DSM stage streams clouds by chunks and spills grid blocks to disk on large sites:
    forcing both on the tiny site gives the same DSM and cloud as the in-memory path."""
    import shutil

    from recon_core.io.ply import read_ply
    from recon_core.io.raster import read_dsm

    state, _ = tiny_run
    out = tmp_path / "out"
    shutil.copytree(state.out, out)
    cfg = preset("tiny").with_overrides({"dsm.chunk_points": 5000, "dsm.spill_above_points": 0})
    run(state.site.root, out, cfg, until="dsm", redo_from="dsm")
    assert not list(out.glob("dsm_blocks_*")), "spilled blocks were not removed"
    H0, g0 = read_dsm(state.out / "dsm.tif")
    H1, g1 = read_dsm(out / "dsm.tif")
    assert g0 == g1
    np.testing.assert_array_equal(H0, H1)
    x0, _, _ = read_ply(state.out / "cloud.ply")
    x1, _, _ = read_ply(out / "cloud.ply")
    assert len(x0) > 5000
    np.testing.assert_array_equal(x0, x1)
