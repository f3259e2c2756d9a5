"""GCPs as CSV: round trip with gcps.geojson, projected coordinates, and one-line refusals."""

from __future__ import annotations

import json

import numpy as np
import pytest

from recon_core.cli import main
from recon_core.errors import InputError
from recon_core.io.gcps import read_gcps_geojson
from recon_core.io.gcps_csv import read_gcps_csv, write_gcps_csv
from tests.conftest import gcp_feature


def test_geojson_csv_geojson_round_trip_keeps_every_gcp(small_site, tmp_path):
    fc = json.loads((small_site / "gcps.geojson").read_text())
    fc["features"].append(gcp_feature("C2", 10.001, 45.002, 130.5, {"a.tif": [10.25, 20.75]}, role="check"))
    fc["features"].append(gcp_feature("N3", 10.002, 45.001, 99.0, {}))
    (small_site / "gcps.geojson").write_text(json.dumps(fc))
    csv_path, back = tmp_path / "g.csv", tmp_path / "g.geojson"
    assert main(["gcps", "convert", str(small_site / "gcps.geojson"), str(csv_path),
                 "--site", str(small_site)]) == 0
    assert main(["gcps", "convert", str(csv_path), str(back), "--site", str(small_site)]) == 0
    a, b = read_gcps_geojson(small_site / "gcps.geojson"), read_gcps_geojson(back)
    assert [g.id for g in a] == [g.id for g in b]
    for x, y in zip(a, b):
        assert np.allclose(x.llh, y.llh, atol=1e-8) and x.role == y.role
        assert sorted(x.observations) == sorted(y.observations)
        for name, xy in x.observations.items():
            assert np.allclose(xy, y.observations[name], atol=1e-9), (x.id, name)


def test_projected_coordinates_in_and_out(tmp_path):
    from recon_core.io.gcps import GCP

    g = GCP("U1", 10.5, 45.25, 300.0, "control", 0.2, {"a.tif": (1.0, 2.0)})
    p = write_gcps_csv(tmp_path / "utm.csv", [g], epsg=32632)
    text = p.read_text()
    assert ",32632," in text and "10.5" not in text.splitlines()[1].split(",")[2]
    (r,) = read_gcps_csv(p)
    assert abs(r.lon - 10.5) < 1e-8 and abs(r.lat - 45.25) < 1e-8 and r.sigma_m == 0.2
    # a spreadsheet export: semicolons, other column order, E/N given by --epsg
    (tmp_path / "sheet.csv").write_text("ID;h;x;y;Image;Col;Row\n"
                                        "P1;300;{:.3f};{:.3f};a.tif;5;6\n".format(
                                            *map(float, text.splitlines()[1].split(",")[2:4])))
    (s,) = read_gcps_csv(tmp_path / "sheet.csv", default_epsg=32632)
    assert abs(s.lon - 10.5) < 1e-7 and s.observations == {"a.tif": (5.0, 6.0)} and s.role == "control"


def test_a_height_known_worse_round_trips(tmp_path):
    """sigma_h_m: an optional column, written only when a GCP has one."""
    from recon_core.io.gcps import GCP

    plain = GCP("A", 10.5, 45.25, 300.0, "control", None, {"a.tif": (1.0, 2.0)})
    assert "sigma_h_m" not in write_gcps_csv(tmp_path / "a.csv", [plain]).read_text()
    roof = GCP("B", 10.6, 45.25, 310.0, "control", None, {"a.tif": (3.0, 4.0), "b.tif": (5.0, 6.0)}, sigma_h_m=4.5)
    back = read_gcps_csv(write_gcps_csv(tmp_path / "b.csv", [plain, roof]))
    assert [g.sigma_h_m for g in back] == [None, 4.5] and back[1].observations == roof.observations


@pytest.mark.parametrize("text, words", [
    ("id,x,y\nA,1,2\n", "missing column(s) h"),
    ("id,x,y,h\nA,1,north,3\n", "line 2: y 'north' is not a number"),
    ("id,x,y,h\nA,500000,4000000,3\n", "line 2: lon/lat"),
    ("id,x,y,h,role\nA,1,2,3,ground\n", "line 2: role 'ground'"),
    ("id,x,y,h,image,col,row\nA,1,2,3,a.tif,1,2\nA,1,2,4,b.tif,1,2\n", "line 3: A has other ground"),
    ("id,x,y,h,image,col,row\nA,1,2,3,a.tif,1,2\nA,1,2,3,a.tif,5,5\n", "line 3: A observed twice"),
    ("id,x,y,h,epsg\nA,1,2,3,999999\n", "line 2: cannot use EPSG:999999"),
    ("id,x,y,h,sigma_h_m\nA,1,2,3,-1\n", "line 2: sigma_h_m must be positive"),
    ("id,x,y,h,epsg\nA,1e9,1e9,3,32632\n", "line 2: E, N"),
    ("id,x,y,h\n\nA,1,2,3\n\nB,1,north,3\n", "line 5: y 'north'"),
])
def test_bad_csv_is_refused_naming_the_line(tmp_path, text, words):
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(InputError) as e:
        read_gcps_csv(p)
    assert words in str(e.value) and "bad.csv" in str(e.value)


def test_convert_checks_observations_against_the_site(small_site, tmp_path, capsys):
    p = tmp_path / "g.csv"
    p.write_text("id,x,y,h,image,col,row\nA,10,45,3,a.tif,64.5,2\n")          # a.tif is 64 x 48
    assert main(["gcps", "convert", str(p), str(tmp_path / "g.geojson"), "--site", str(small_site)]) == 2
    err = capsys.readouterr().err
    assert "outside a.tif" in err and not (tmp_path / "g.geojson").exists()


def test_csv_export_refuses_what_it_cannot_hold(small_site, tmp_path, capsys):
    from recon_core.io.gcps import GCP, write_gcps_geojson

    g = GCP("P1", 10.0, 45.0, 100.0, "control", None, {"a.tif": (1.0, 2.0)},
            affine_picked={0: np.array([1.0, 2.0, 3.0])})
    write_gcps_geojson(tmp_path / "work.geojson", [g])
    assert main(["gcps", "convert", str(tmp_path / "work.geojson"), str(tmp_path / "w.csv")]) == 2
    assert "picked on a cloud" in capsys.readouterr().err and not (tmp_path / "w.csv").exists()
    g.affine_picked, g.enabled = {}, False
    write_gcps_geojson(tmp_path / "work.geojson", [g])
    assert main(["gcps", "convert", str(tmp_path / "work.geojson"), str(tmp_path / "w.csv")]) == 2
    assert "P1 is disabled" in capsys.readouterr().err and not (tmp_path / "w.csv").exists()
    assert main(["gcps", "convert", str(small_site / "gcps.geojson"), str(tmp_path / "x.csv"),
                 "--epsg", "999999"]) == 2
    err = capsys.readouterr().err
    assert "--epsg 999999" in err and "Traceback" not in err
