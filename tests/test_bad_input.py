"""Bad input, case by case: one line naming the file (or option) and the problem, exit code 2,
before any compute, never a traceback. Each case edits a small valid site, then runs the
command line in-process."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from recon_core.cli import main
from tests.conftest import gcp_feature, write_tiff


def _site_json(site: Path, doc) -> None:
    (site / "site.json").write_text(json.dumps(doc))


def _gcps(site: Path, edit) -> None:
    doc = json.loads((site / "gcps.geojson").read_text())
    edit(doc)
    (site / "gcps.geojson").write_text(json.dumps(doc))


def _four_control_gcps(site: Path, heights=(100.0, 101.0, 140.0, 103.0)) -> None:
    feats = [gcp_feature(f"G{k}", 10.0 + 1e-4 * k, 45.0 + 2e-4 * (k % 2), heights[k],
                         {"a.tif": [3.0 + k, 4.0], "b.tif": [5.5 + k, 6.5]}) for k in range(4)]
    (site / "gcps.geojson").write_text(json.dumps({"type": "FeatureCollection", "features": feats}))


def _coplanar_control_gcps(site: Path) -> None:
    # h = 100 + k while the easting grows with k and the northing alternates: one plane
    _four_control_gcps(site, heights=(100.0, 101.0, 102.0, 103.0))


def _gcps_dir(site: Path) -> None:
    (site / "gcps.geojson").unlink()
    (site / "gcps.geojson").mkdir()


# (case id, how to break the site, extra command-line arguments, the file or word the message names,
#  words of the problem)
CASES = [
    ("site.json unknown EPSG", lambda s: _site_json(s, {"crs_epsg": 999999}), [], "site.json", "EPSG"),
    ("site.json geographic EPSG", lambda s: _site_json(s, {"crs_epsg": 4326}), [], "site.json", "projected"),
    ("site.json resolution text", lambda s: _site_json(s, {"resolution_m": "fine"}), [], "site.json",
     "resolution_m"),
    ("site.json bounds as strings", lambda s: _site_json(s, {"crs_epsg": 32632, "bounds": ["1", "2", "3", "4"]}),
     [], "site.json", "bounds"),
    ("site.json bounds in degrees", lambda s: _site_json(s, {"crs_epsg": 32632,
                                                             "bounds": [9.9, 44.9, 10.1, 45.1]}),
     [], "site.json", "degrees"),
    ("site.json bounds far from the GCPs", lambda s: _site_json(s, {"crs_epsg": 32632,
                                                                    "bounds": [0, 0, 1000, 1000]}),
     [], "site.json", "far from every GCP"),
    ("gcps sigma not a number", lambda s: _gcps(s, lambda d: d["features"][0]["properties"].update(sigma_m="x")),
     [], "gcps.geojson", "sigma_m"),
    ("gcps height sigma negative", lambda s: _gcps(s, lambda d: d["features"][0]["properties"].update(sigma_h_m=-1)),
     [], "gcps.geojson", "sigma_h_m"),
    ("gcps unknown crs_epsg", lambda s: _gcps(s, lambda d: d.update(crs_epsg=999999)), [], "gcps.geojson",
     "EPSG"),
    ("gcps properties a list", lambda s: _gcps(s, lambda d: d["features"][0].update(properties=[1, 2])),
     [], "gcps.geojson", "properties"),
    ("gcps file is a folder", _gcps_dir, [], "gcps.geojson", "not a file"),
    ("too few control GCPs", lambda s: None, [], "gcps.geojson", "4 needed"),
    ("no GCP file", lambda s: (s / "gcps.geojson").unlink(), [], "gcps.geojson", "no GCP"),
    ("GCPs only as CSV", lambda s: ((s / "gcps.csv").write_text("id,x,y,h\n"), (s / "gcps.geojson").unlink()),
     [], "gcps.geojson", "gcps.csv is not read: `aerec gcps convert"),
    ("unknown preset", _four_control_gcps, ["--preset", "huge"], "--preset", "huge"),
    ("negative tile size", _four_control_gcps, ["--tile-size", "-5"], "--tile-size", "64"),
    ("negative workers", _four_control_gcps, ["--workers", "-1"], "--workers", "at least 1"),
    ("unknown stage", _four_control_gcps, ["--stage", "dsn"], "stage", "dsn"),
    ("coplanar control GCPs", _coplanar_control_gcps, [], "gcps.geojson", "height scale is undetermined"),
    ("a blank image", lambda s: write_tiff(s / "images" / "b.tif", np.full((48, 64), 812, np.uint16),
                                           when="2020:01:03 10:00:00"), [], "b.tif", "is blank"),
]


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_run_refuses_bad_input_in_one_line(case, small_site, tmp_path, capsys):
    _, breaks, extra, names, words = case
    breaks(small_site)
    out = tmp_path / "out"
    code = main(["run", str(small_site), "--out", str(out), "--quiet", *extra])
    err = capsys.readouterr().err
    assert code == 2, err
    lines = [ln for ln in err.strip().splitlines() if ln.startswith("aerec: error:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    assert names in lines[0] and words in lines[0], lines[0]
    assert not (out / "affine").exists() and not (out / "stages").exists()    # nothing computed


def test_info_shows_site_json_problems_too(small_site, capsys):
    _site_json(small_site, {"crs_epsg": 999999})
    assert main(["info", str(small_site)]) == 2
    assert "site.json" in capsys.readouterr().err


@pytest.mark.parametrize("target", ["file", "missing_parent_is_a_file"])
def test_unwritable_output(small_site, tmp_path, capsys, target):
    _four_control_gcps(small_site)
    f = tmp_path / "f"
    f.write_text("x")
    out = f if target == "file" else f / "sub"
    assert main(["run", str(small_site), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("aerec: error:") == 1 and "Traceback" not in err and str(f) in err


def test_eval_out_must_be_a_folder_and_help_works(tmp_path, capsys):
    f = tmp_path / "f.txt"
    f.write_text("x")
    assert main(["eval", "a.tif", "b.tif", "--out", str(f)]) == 2
    assert "--out must be a folder" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        main(["eval", "--help"])
    assert e.value.code == 0 and "ground-truth" in capsys.readouterr().out


def test_version(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.startswith("aerec ")


def test_config_dump_round_trips_and_a_config_file_is_checked(tmp_path, capsys, small_site):
    import tomllib

    from recon_core.config import config_from_dict, preset

    assert main(["config", "--dump", "--preset", "tiny"]) == 0
    text = capsys.readouterr().out
    assert "[sgbm]" in text and "# d: tile side" in text
    # every field's whole comment, continued on comment lines under it (not its first line only)
    assert "SIFT's own positions are off" in text and "0 = off" in text.split("refine_half_px")[1].split("\n\n")[0]
    assert config_from_dict(tomllib.loads(text)) == preset("tiny")
    old = text.replace("[bundle]\n", "[bundle]\nsmoothness_weight = 0.0\n").replace(
        "[matching]\n", "[matching]\nmin_parallax_ratio = 0.0\n")        # removed: read, skipped
    assert old.count("\n") == text.count("\n") + 2 and config_from_dict(tomllib.loads(old)) == preset("tiny")
    for body, words in [("[tiling]\ntile_size = 'x'\n", "tiling.tile_size must be int"),
                        ("[tiling]\nbogus = 3\n", "unknown parameter tiling.bogus"),
                        ("[tiling\n", "malformed TOML")]:
        f = tmp_path / "c.toml"
        f.write_text(body)
        assert main(["run", str(small_site), "--out", str(tmp_path / "o"), "--config", str(f)]) == 2
        err = capsys.readouterr().err
        assert err.count("aerec: error:") == 1 and str(f) in err and words in err, err


def test_coplanar_control_gcps_pass_with_the_explicit_override(small_site, tmp_path):
    from recon_core.config import Config
    from recon_core.preflight import preflight

    _coplanar_control_gcps(small_site)
    cfg = Config()
    cfg.upgrade.allow_flat_gcps = True
    assert preflight(small_site, tmp_path / "out", cfg) == []
    _four_control_gcps(small_site)                     # 40 m off the others' plane: accepted
    assert preflight(small_site, tmp_path / "out2", Config()) == []


def _views(site: Path) -> None:
    """Each image's viewing direction in its sidecar (the site format's optional `view`)."""
    for name, (inc, az) in (("a", (12.0, 100.0)), ("b", (18.0, 260.0))):
        (site / "images" / f"{name}.json").write_text(json.dumps({"view": {"incidence_deg": inc, "azimuth_deg": az}}))


def test_the_images_viewing_directions_hold_what_flat_or_three_gcps_cannot(small_site, tmp_path, capsys):
    """With the images' viewing directions, GCPs on one plane and 3 control GCPs pass the
    pre-flight (the images hold the height scale); collinear GCPs are refused all the same."""
    from recon_core.config import Config
    from recon_core.preflight import preflight

    _coplanar_control_gcps(small_site)
    _views(small_site)
    assert preflight(small_site, tmp_path / "out", Config()) == []
    _gcps(small_site, lambda d: d["features"][3]["properties"].update(role="check"))
    assert preflight(small_site, tmp_path / "out", Config()) == []
    # the same 3 without the images' directions (the parameter off): refused, saying what would do
    cfg = Config()
    cfg.upgrade.view_sigma_deg = 0.0
    with pytest.raises(Exception, match="3 needed|4 needed|enough control GCPs"):
        preflight(small_site, tmp_path / "out", cfg)
    feats = [gcp_feature(f"L{k}", 10.0 + 1e-4 * k, 45.0 + 1e-4 * k, 100.0 + k,
                         {"a.tif": [3.0 + k, 4.0], "b.tif": [5.5 + k, 6.5]}) for k in range(4)]
    (small_site / "gcps.geojson").write_text(json.dumps({"type": "FeatureCollection", "features": feats}))
    assert main(["run", str(small_site), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("aerec: error:") == 1 and "lie on one line" in err and "gcps.geojson" in err


def test_run_says_which_gcp_file_it_uses_when_the_sites_was_edited_later(small_site, tmp_path):
    import os
    import shutil

    from recon_core.config import Config
    from recon_core.preflight import preflight

    _four_control_gcps(small_site)
    out = tmp_path / "out"
    out.mkdir()
    shutil.copy(small_site / "gcps.geojson", out / "gcps.geojson")    # the viewer's working set
    t = (out / "gcps.geojson").stat().st_mtime
    os.utime(small_site / "gcps.geojson", (t + 10, t + 10))
    assert preflight(small_site, out, Config()) == []                 # edited later, same content
    _four_control_gcps(small_site, heights=(100.0, 101.0, 150.0, 103.0))
    os.utime(small_site / "gcps.geojson", (t + 20, t + 20))
    notes = preflight(small_site, out, Config())
    assert len(notes) == 1 and f"uses {out / 'gcps.geojson'}" in notes[0] and "delete" in notes[0]


def test_info_shows_what_run_would_refuse_as_warnings(small_site, capsys):
    _coplanar_control_gcps(small_site)
    assert main(["info", str(small_site)]) == 0
    out = capsys.readouterr().out
    assert "warning: `aerec run` would refuse: refused: the control GCPs lie within" in out
    _gcps(small_site, lambda d: [f["properties"].update(role="check") for f in d["features"][1:]])
    assert main(["info", str(small_site)]) == 0
    assert "1 control GCP(s) observed in >= 2 of its images, 4 needed" in capsys.readouterr().out


def test_a_flat_group_is_a_warning_when_another_group_can_be_upgraded(tmp_path):
    """Two date groups: one with a coplanar control set, one with a good one. The upgrade would
    refuse only the flat group, so the run warns about it instead of refusing everything."""
    import numpy as np

    from recon_core.config import Config
    from recon_core.preflight import preflight
    from tests.conftest import write_tiff

    site = tmp_path / "site"
    rng = np.random.default_rng(0)
    for name, day in (("a", "01"), ("b", "02"), ("c", "20"), ("d", "21")):
        write_tiff(site / "images" / f"{name}.tif", rng.integers(0, 2047, (48, 64), dtype=np.uint16),
                   when=f"2020:01:{day} 10:00:00")
    feats = []
    for k in range(4):
        lon, lat = 10.0 + 1e-4 * k, 45.0 + 2e-4 * (k % 2)
        feats.append(gcp_feature(f"F{k}", lon, lat, 100.0 + k, {"a.tif": [3.0 + k, 4.0], "b.tif": [5.0 + k, 6.0]}))
        feats.append(gcp_feature(f"G{k}", lon, lat, (100.0, 101.0, 140.0, 103.0)[k],
                                 {"c.tif": [3.0 + k, 4.0], "d.tif": [5.0 + k, 6.0]}))
    (site / "gcps.geojson").write_text(json.dumps({"type": "FeatureCollection", "features": feats}))
    notes = preflight(site, tmp_path / "out", Config())
    assert len(notes) == 1 and notes[0].startswith("group 0 will not be upgraded: refused:")


def test_a_full_disk_is_one_line_and_leaves_nothing_half_written(tiny_site, tmp_path, capsys, monkeypatch):
    """The disk fills while the sparse model is written: one line naming the file, exit 1, no
    half-written model and no scratch (the write was atomic)."""
    import errno

    import recon_core.io.models as models
    from recon_core.io.files import atomic_path
    from recon_core.io.layout import OutLayout

    def full_disk(path, obj, indent=1):
        with atomic_path(path) as tmp:
            tmp.write_text('{"group": 0, "ima')                  # part of it went to disk
            raise OSError(errno.ENOSPC, "No space left on device", str(tmp))

    monkeypatch.setattr(models, "write_json", full_disk)
    out = tmp_path / "out"
    code = main(["run", str(tiny_site), "--out", str(out), "--preset", "tiny", "--stage", "sparse", "--quiet"])
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err, err
    lines = [ln for ln in err.strip().splitlines() if ln.startswith("aerec: error:")]
    assert len(lines) == 1 and "No space left on device" in lines[0]
    assert f"{OutLayout(out).cameras(0)}: " in lines[0]                  # the file, not its temporary
    lay = OutLayout(out)
    assert not lay.cameras(0).exists() and lay.scratch() == []


def test_gcps_seen_across_date_groups_count_when_the_groups_are_reconstructed_jointly(tmp_path):
    """Each GCP seen once in each of two date groups: no group has a control GCP of its own in 2
    of its images, but the joint reconstruction (one frame, one upgrade) can use all four. The
    run goes on, saying so; with the joint reconstruction off it refuses before any compute."""
    import numpy as np

    from recon_core.config import Config
    from recon_core.errors import InputError
    from recon_core.preflight import preflight
    from tests.conftest import write_tiff

    site = tmp_path / "site"
    rng = np.random.default_rng(0)
    for name, day in (("a", "01"), ("b", "02"), ("c", "20"), ("d", "21")):
        write_tiff(site / "images" / f"{name}.tif", rng.integers(0, 2047, (48, 64), dtype=np.uint16),
                   when=f"2020:01:{day} 10:00:00")
    feats = [gcp_feature(f"J{k}", 10.0 + 1e-4 * k, 45.0 + 2e-4 * (k % 2), (100.0, 110.0, 135.0, 104.0)[k],
                         {"a.tif": [3.0 + k, 4.0], "c.tif": [5.0 + k, 6.0]}) for k in range(4)]
    (site / "gcps.geojson").write_text(json.dumps({"type": "FeatureCollection", "features": feats}))
    notes = preflight(site, tmp_path / "out", Config())
    assert len(notes) == 2 and all("through the joint reconstruction (4 control GCPs" in n for n in notes)
    off = Config().with_overrides({"sfm.joint_groups": False})
    with pytest.raises(InputError, match="no date group has enough control GCPs"):
        preflight(site, tmp_path / "out", off)


@pytest.mark.parametrize("body, words", [
    ("[tiling]\ntile_size = -5\n", "tiling.tile_size = -5: must be >= 64"),
    ("[tiling]\noverlap = 5000\n", "tiling.overlap = 5000"),
    ("seed = -3\n", "seed = -3: must be >= 0"),
    ("[bundle]\nloss = 'bogus'\n", "bundle.loss = 'bogus': choose one of linear, huber, cauchy"),
    ("[bundle]\nsolver = 'cholmod'\n", "bundle.solver = 'cholmod': choose one of auto, dense, sparse"),
    ("[dense]\nworkers = -1\n", "dense.workers = -1"),
    ("[dense]\nmatcher = 'nope'\n", "dense.matcher = 'nope': choose one of sgbm"),
    ("[dsm]\nstat = 'foo'\n", "dsm.stat = 'foo'"),
    ("[dsm]\nresolution_m = -1.0\n", "dsm.resolution_m = -1.0: must be >= 0.01"),
    ("[matching]\nratio = 5.0\n", "matching.ratio = 5.0"),
    ("[sgbm]\nblock_size = 4\n", "sgbm.block_size = 4: must be odd"),
    ("[sfm]\ncorrection_rounds = -1\n", "sfm.correction_rounds = -1: must be >= 0"),
    ("[upgrade]\norbit_altitude_km = 0.0\n", "upgrade.orbit_altitude_km = 0.0: must be >= 100"),
], ids=lambda v: v.split("\n")[0] if "\n" in v else None)
def test_config_values_are_checked_before_any_compute(body, words, small_site, tmp_path, capsys):
    """Each of these reached a stage and ended in a traceback there (some after sparse, dense and
    the upgrade): now one line naming the file and the field, exit 2, nothing written."""
    f = tmp_path / "c.toml"
    f.write_text(body)
    out = tmp_path / "o"
    assert main(["run", str(small_site), "--out", str(out), "--config", str(f), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("aerec: error:") == 1 and "Traceback" not in err and str(f) in err and words in err, err
    assert not out.exists()


def test_every_preset_passes_the_value_checks():
    from recon_core.config import PRESETS, preset
    from recon_core.preflight import check_config

    for name in PRESETS:
        check_config(preset(name))


@pytest.mark.parametrize("argv, words", [
    (["--seed", "-1"], "--seed must be >= 0"),
    (["--out", ""], "--out is empty"),
])
def test_command_line_values(argv, words, small_site, tmp_path, capsys):
    args = ["run", str(small_site), "--quiet"] + (argv if "--out" in argv else argv + ["--out", str(tmp_path / "o")])
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.count("aerec: error:") == 1 and words in err, err


def test_outputs_under_a_file_or_nowhere_are_refused_before_compute(small_site, tmp_path, capsys):
    f = tmp_path / "f.txt"
    f.write_text("x")
    gt = small_site / "gt_dsm.tif"
    for argv, words in [(["eval", str(gt), str(gt), "--out", str(f / "x")], "cannot create or write"),
                        (["gcps", "convert", str(small_site / "gcps.geojson"), str(f / "o.csv")], "is a file"),
                        (["gcps", "convert", str(small_site / "gcps.geojson"), str(tmp_path / "no" / "o.csv")],
                         "no such folder")]:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.count("aerec: error:") == 1 and words in err and "Traceback" not in err, err


def test_a_closed_pipe_ends_quietly(small_site):
    """`aerec info SITE | head -1`: the reader leaves early; no BrokenPipeError traceback."""
    import subprocess
    import sys

    r = subprocess.run(f"{sys.executable} -m recon_core.cli info {small_site} | head -1",
                       shell=True, capture_output=True, text=True)
    assert r.stdout.count("\n") == 1 and "Traceback" not in r.stderr, r.stderr


@pytest.mark.parametrize("message", [
    "129710 requested and 102939 written",          # numpy's short write
    # numpy's failed allocation of the file's space (tofile of a cloud chunk in the DSM stage
    # of `large`, measured on this machine's full disk)
    "Not enough free space to write 108000000 bytes after offset 3971899894",
])
def test_a_short_write_is_reported_as_a_full_disk(message, tiny_site, tmp_path, capsys, monkeypatch):
    """numpy's write errors on a full disk carry no errno: one line, not a traceback."""
    import recon_core.io.models as models

    def short(path, obj, indent=1):
        raise OSError(message)

    monkeypatch.setattr(models, "write_json", short)
    code = main(["run", str(tiny_site), "--out", str(tmp_path / "o"), "--preset", "tiny", "--stage",
                 "sparse", "--quiet"])
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err and "is the disk full?" in err, err


def test_a_broken_pipe_that_is_not_stdout_is_not_swallowed(monkeypatch):
    """Only a reader leaving stdout ends quietly; a pipe to a dead worker is a real failure."""
    import recon_core.cli as cli

    def broken(args):
        raise BrokenPipeError(32, "Broken pipe")

    monkeypatch.setattr(cli, "cmd_info", broken)
    with pytest.raises(BrokenPipeError):
        main(["info", "x"])


def _dem(path: Path, lon0: float, lat0: float, crs: str | None = "EPSG:4326", fill: float = 120.0) -> None:
    import rasterio
    from rasterio.transform import from_origin

    with rasterio.open(path, "w", driver="GTiff", width=20, height=20, count=1, dtype="float32",
                       crs=crs, transform=from_origin(lon0, lat0, 1e-3, 1e-3)) as dst:
        dst.write(np.full((20, 20), fill, np.float32), 1)


def test_a_missing_reference_dem_is_refused_whatever_the_stage(small_site, tmp_path, capsys):
    """--stage sparse with --reference-dem MISSING: the run was asked to use it, it is refused."""
    _four_control_gcps(small_site)
    code = main(["run", str(small_site), "--out", str(tmp_path / "o"), "--stage", "sparse", "--quiet",
                 "--reference-dem", str(tmp_path / "srtm.tif")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "srtm.tif" in err[0] and "no such file" in err[0], err


DEM_CASES = [
    ("missing", lambda d: None, "no such file"),
    ("not a raster", lambda d: d.write_text("not a DEM"), "not a raster"),
    ("no CRS", lambda d: _dem(d, 9.99, 45.01, crs=None), "no CRS"),
    ("elsewhere", lambda d: _dem(d, 20.0, 10.0), "no height where the site is: it lies"),
    ("all nodata", lambda d: _dem(d, 9.99, 45.01, fill=np.nan), "no height anywhere"),
    ("a local CRS", lambda d: _dem(d, 9.99, 45.01, crs='LOCAL_CS["arbitrary",UNIT["metre",1]]'),
     "cannot be reached from WGS84"),
]


@pytest.mark.parametrize("case", DEM_CASES, ids=[c[0] for c in DEM_CASES])
def test_a_bad_reference_dem_is_refused_in_one_line_before_any_compute(case, small_site, tmp_path, capsys):
    _, make, words = case
    _four_control_gcps(small_site)
    dem = tmp_path / "dem.tif"
    make(dem)
    out = tmp_path / "out"
    code = main(["run", str(small_site), "--out", str(out), "--quiet", "--reference-dem", str(dem)])
    err = capsys.readouterr().err
    lines = [ln for ln in err.strip().splitlines() if ln.startswith("aerec: error:")]
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert "dem.tif" in lines[0] and words in lines[0], lines[0]
    assert not (out / "affine").exists() and not (out / "stages").exists()
    # the DEM that covers the GCPs passes the check (the run itself is not started here)
    _dem(dem, 9.99, 45.01)
    from recon_core.config import preset
    from recon_core.preflight import preflight

    preflight(small_site, out, preset("default").with_overrides({"upgrade.reference_dem": str(dem)}))


def test_a_reference_dem_named_in_a_toml_file_is_that_files_neighbour(tmp_path, monkeypatch):
    from recon_core.config import config_from_toml

    (tmp_path / "cfg").mkdir()
    (tmp_path / "cfg" / "my.toml").write_text('[upgrade]\nreference_dem = "srtm.tif"\n')
    monkeypatch.chdir(tmp_path)
    cfg = config_from_toml(tmp_path / "cfg" / "my.toml")
    assert cfg.upgrade.reference_dem == str((tmp_path / "cfg" / "srtm.tif").resolve())
