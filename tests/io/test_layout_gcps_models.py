"""The OUT layout, the GCP files (picked affine positions included) and the model files."""

from __future__ import annotations

import json

import numpy as np
import pytest

from recon_core.errors import InputError
from recon_core.geometry.geodesy import LocalFrame
from recon_core.io.gcps import GCP, picked_positions, read_gcps_geojson, working_gcp_file, write_gcps_geojson
from recon_core.io.layout import OutLayout
from recon_core.io.models import load_model, load_upgrade, save_model, save_upgrade


def test_layout_lists_what_exists(tmp_path):
    lay = OutLayout(tmp_path)
    assert lay.model_groups() == [] and lay.upgraded_groups() == [] and not lay.is_output()
    for g in (2, 0):
        lay.cameras(g).parent.mkdir(parents=True)
        lay.cameras(g).write_text("{}")
    lay.group_dir(5).mkdir()                                   # no cameras.json: not a model
    assert lay.model_groups() == [0, 2] and lay.is_output()
    assert lay.dense_ply(2) == tmp_path / "affine" / "group_2" / "dense.ply"


def test_picked_positions_round_trip_and_working_set(tmp_path):
    g = GCP("G1", 30.0, 31.2, 55.5, "check", 0.2, {"a.tif": (1.25, 2.5)},
            affine_picked={1: np.array([1.0, 2.0, 3.5])})
    site, out = tmp_path / "site", tmp_path / "out"
    site.mkdir(), out.mkdir()
    write_gcps_geojson(site / "gcps.geojson", [g])
    assert working_gcp_file(site, out) == site / "gcps.geojson"
    write_gcps_geojson(out / "gcps.geojson", [g], written_by="test")
    assert working_gcp_file(site, out) == out / "gcps.geojson"
    back = read_gcps_geojson(out / "gcps.geojson")[0]
    assert back.role == "check" and back.observations == {"a.tif": (1.25, 2.5)}
    np.testing.assert_array_equal(back.affine_picked[1], [1.0, 2.0, 3.5])
    assert set(picked_positions([back], 1)) == {"G1"} and picked_positions([back], 0) == {}
    doc = json.loads((out / "gcps.geojson").read_text())
    doc["features"][0]["properties"]["affine_picked"] = {"x": [1, 2]}
    (out / "gcps.geojson").write_text(json.dumps(doc))
    with pytest.raises(InputError, match="affine_picked"):
        read_gcps_geojson(out / "gcps.geojson")


def test_disabled_gcp_round_trips_and_a_bad_enabled_value_is_refused(tmp_path):
    on = GCP("G1", 30.0, 31.2, 55.5, "control", None, {"a.tif": (1.0, 2.0)})
    off = GCP("G2", 30.1, 31.3, 56.5, "check", None, {"a.tif": (3.0, 4.0)}, enabled=False)
    write_gcps_geojson(tmp_path / "g.geojson", [on, off])
    doc = json.loads((tmp_path / "g.geojson").read_text())
    props = [f["properties"] for f in doc["features"]]
    assert "enabled" not in props[0] and props[1]["enabled"] is False    # written only when false
    back = read_gcps_geojson(tmp_path / "g.geojson")
    assert [g.enabled for g in back] == [True, False] and back[1].role == "check"
    props[1]["enabled"] = "no"
    (tmp_path / "g.geojson").write_text(json.dumps(doc))
    with pytest.raises(InputError, match="enabled must be true or false"):
        read_gcps_geojson(tmp_path / "g.geojson")


def test_model_and_upgrade_files_round_trip(tiny_run, tmp_path):
    state, _ = tiny_run
    m = state.models[0]
    save_model(m, tmp_path)
    back = load_model(OutLayout(tmp_path), 0)
    np.testing.assert_array_equal(back.cams, m.cams)
    np.testing.assert_array_equal(back.X[back.has_point], m.X[m.has_point])
    assert [t.id for t in back.tiles] == [t.id for t in m.tiles]
    frame = LocalFrame(30.0, 31.2, 10.0)
    H = np.eye(4)
    save_upgrade(tmp_path, {0: {"H": H.tolist()}, 3: {"H": (2 * H).tolist()}}, frame)
    save_upgrade(tmp_path, {0: {"H": H.tolist()}}, frame)             # group 3 not upgraded now
    maps, fr = load_upgrade(tmp_path)
    assert list(maps) == [0] and fr.to_dict() == frame.to_dict()
    np.testing.assert_array_equal(maps[0].H, H)
    assert maps[0].warp is None
