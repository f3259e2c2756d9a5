"""Products say what their numbers are: the DSM's vertical reference and units, the clouds' frame."""

from __future__ import annotations

import numpy as np
import rasterio

from recon_core.io.models import affine_frame_comments
from recon_core.io.ply import read_ply, write_ply
from recon_core.io.raster import Grid, read_dsm, write_dsm


def test_dsm_carries_its_vertical_datum_and_units(tmp_path):
    grid = Grid(32631, 500000.0, 4500000.0, 0.5, 8, 6)
    H = np.arange(48, dtype=np.float32).reshape(6, 8)
    p = write_dsm(tmp_path / "dsm.tif", H, grid)
    with rasterio.open(p) as ds:
        tags = ds.tags()
        assert "ellipsoid" in tags["VERTICAL_DATUM"] and tags["VERTICAL_UNITS"] == "metre"
        assert ds.descriptions[0] == "height above the WGS84 ellipsoid" and ds.units[0] == "metre"
    H2, g2 = read_dsm(p)                              # still a plain DSM to read back
    assert np.array_equal(H2, H) and g2 == grid


def test_ply_header_names_the_frame_and_still_reads(tmp_path):
    xyz = np.random.default_rng(0).normal(size=(50, 3))
    p = write_ply(tmp_path / "c.ply", xyz, comments=affine_frame_comments(2))
    head = p.read_bytes().split(b"end_header")[0].decode()
    assert "comment frame affine reconstruction of date group 2" in head
    assert "upgrade/group_2.json" in head
    got, colors, extra = read_ply(p)
    assert np.array_equal(got, xyz) and colors is None and not extra
