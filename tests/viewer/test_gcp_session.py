"""The GCP working set: atomic saves, undo and redo of every edit, ground coordinates."""

from __future__ import annotations

import numpy as np
import pytest

from aerec_viewer.gcp_session import (
    GcpError,
    add_observation,
    delete_gcp,
    edit_gcp,
    import_site_gcps,
    new_gcp,
    open_session,
    redo,
    remove_observation,
    set_affine_position,
    undo,
)


def test_gcp_session_edits_are_saved_atomically_and_restored(small_site, tmp_path):
    from recon_core.io.gcps import read_gcps_geojson
    from recon_core.io.site import load_site

    site = load_site(small_site)
    out = tmp_path / "out"
    s = open_session(out, site)
    assert s.ids == ["G1"] and (out / "gcps.geojson").exists()
    assert not (small_site / "gcps.geojson").read_text().count("written_by")   # site untouched
    g = new_gcp(s, x=10.0001, y=45.0002, h=120.0, role="check")
    assert g.id == "GCP-01"
    add_observation(s, "GCP-01", "a.tif", 10.25, 20.5)
    add_observation(s, "GCP-01", "b.tif", 11.0, 21.0)
    with pytest.raises(GcpError):
        add_observation(s, "GCP-01", "a.tif", 64.0, 3.0)   # outside the 64 x 48 image
    with pytest.raises(GcpError):
        new_gcp(s, "G1", x=0.0, y=0.0, h=0.0)              # duplicate id
    set_affine_position(s, "G1", 0, np.array([1.0, 2.0, 3.0]))
    edit_gcp(s, "GCP-01", new_id="P7", role="control")
    remove_observation(s, "P7", "b.tif")
    # what the core reads back
    gcps = read_gcps_geojson(out / "gcps.geojson", {im.name: im for im in site.images})
    by = {x.id: x for x in gcps}
    assert by["P7"].observations == {"a.tif": (10.25, 20.5)} and by["P7"].role == "control"
    # reopening restores everything, picked positions included
    s2 = open_session(out, site)
    assert s2.ids == ["G1", "P7"] and np.allclose(s2.get("G1").affine_picked[0], [1, 2, 3])
    delete_gcp(s2, "G1")
    assert open_session(out, site).ids == ["P7"]
    assert import_site_gcps(s2) == ["G1"]                 # back from the site's list


def test_every_gcp_edit_can_be_undone_and_redone(small_site, tmp_path):
    """Undo walks back through observations, moves, role changes, cloud picks and deletes, each
    written to OUT/gcps.geojson; a new edit after an undo drops the redo history."""
    from recon_core.io.site import load_site

    site = load_site(small_site)
    out = tmp_path / "out"
    s = open_session(out, site)
    with pytest.raises(GcpError):
        undo(s)                                             # nothing yet
    add_observation(s, "G1", "a.tif", 10.0, 20.0)
    add_observation(s, "G1", "a.tif", 12.0, 22.0)           # a move
    edit_gcp(s, "G1", role="check")
    set_affine_position(s, "G1", 0, np.array([1.0, 2.0, 3.0]))
    delete_gcp(s, "G1")
    assert s.ids == []
    assert undo(s) == "delete G1" and s.ids == ["G1"]
    assert 0 in s.get("G1").affine_picked
    assert undo(s).startswith("pick G1") and not s.get("G1").affine_picked
    assert undo(s) == "edit G1" and s.get("G1").role == "control"
    assert undo(s).startswith("move") and s.get("G1").observations["a.tif"] == (10.0, 20.0)
    assert open_session(out, site).get("G1").observations["a.tif"] == (10.0, 20.0)   # on disk
    assert redo(s).startswith("move") and s.get("G1").observations["a.tif"] == (12.0, 22.0)
    remove_observation(s, "G1", "a.tif")                    # a new edit: no more redo
    with pytest.raises(GcpError):
        redo(s)
    assert undo(s).startswith("remove") and "a.tif" in s.get("G1").observations
    # an edit that fails changes nothing and records nothing
    v = s.version
    with pytest.raises(GcpError):
        edit_gcp(s, "G1", new_id="P9", role="bogus")
    assert s.ids == ["G1"] and s.version == v


def test_a_new_gcp_cannot_reuse_another_gcps_ground_coordinates(small_site, tmp_path):
    from recon_core.io.site import load_site

    s = open_session(tmp_path / "out", load_site(small_site))
    g = s.get("G1")
    with pytest.raises(GcpError, match="already has these ground coordinates"):
        new_gcp(s, x=g.lon, y=g.lat, h=g.h)
    assert s.ids == ["G1"]


def test_gcp_from_projected_coordinates(small_site, tmp_path):
    from recon_core.geometry.geodesy import geodetic_to_projected
    from recon_core.io.site import load_site

    s = open_session(tmp_path / "out", load_site(small_site))
    e, n, h = geodetic_to_projected(np.array([10.5, 45.25, 300.0]), 32632)
    g = new_gcp(s, "U1", x=e, y=n, h=h, epsg=32632)
    assert abs(g.lon - 10.5) < 1e-8 and abs(g.lat - 45.25) < 1e-8 and abs(g.h - 300.0) < 1e-6
    with pytest.raises(GcpError):
        new_gcp(s, "U2", x=500000.0, y=4e6, h=0.0)         # E/N without an EPSG code

