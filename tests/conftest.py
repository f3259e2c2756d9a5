"""Shared fixtures: small hand-made sites, the synthetic `tiny` site, the real shared data."""

from __future__ import annotations

import json
import os
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import rasterio

ROOT = Path(__file__).resolve().parents[1]

# Tests import this folder as the package `tests` (`from tests.conftest import ...`); it has no
# __init__.py, and some wheels install a top-level `tests` package of their own into
# site-packages (pandora_plugin_libsgm and json-checker, brought by the optional `pandora`
# extra), which would win over this folder: bind the name to this folder first.
if "tests" not in sys.modules or list(getattr(sys.modules["tests"], "__path__", [])) != [str(ROOT / "tests")]:
    _pkg = types.ModuleType("tests")
    _pkg.__path__ = [str(ROOT / "tests")]
    sys.modules["tests"] = _pkg

SHARED_DATA = Path(os.environ.get("AEREC_SHARED_DATA", ROOT.parent / "shared" / "data"))


def write_tiff(path: Path, arr: np.ndarray, when: str | None = "2020:01:02 10:00:00", **tags) -> Path:
    """Write a small single-band GeoTIFF with an optional TIFFTAG_DATETIME."""
    path.parent.mkdir(parents=True, exist_ok=True)
    arr = np.asarray(arr)
    with rasterio.open(path, "w", driver="GTiff", width=arr.shape[1], height=arr.shape[0],
                       count=1, dtype=arr.dtype) as ds:
        ds.write(arr, 1)
        if when:
            ds.update_tags(TIFFTAG_DATETIME=when, **tags)
    return path


def gcp_feature(gid: str, lon: float, lat: float, h: float, obs: dict, role: str = "control") -> dict:
    return {"type": "Feature", "geometry": {"type": "Point", "coordinates": [lon, lat, h]},
            "properties": {"id": gid, "role": role, "observations": obs}}


@pytest.fixture
def small_site(tmp_path: Path) -> Path:
    """Two 64 x 48 uint16 images a day apart, one GCP seen in both."""
    rng = np.random.default_rng(0)
    site = tmp_path / "site"
    write_tiff(site / "images" / "a.tif", rng.integers(0, 2047, (48, 64), dtype=np.uint16))
    write_tiff(site / "images" / "b.tif", rng.integers(0, 2047, (48, 64), dtype=np.uint16),
               when="2020:01:03 10:00:00")
    fc = {"type": "FeatureCollection",
          "features": [gcp_feature("G1", 10.0, 45.0, 100.0, {"a.tif": [3.0, 4.0], "b.tif": [5.5, 6.5]})]}
    (site / "gcps.geojson").write_text(json.dumps(fc))
    return site


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared real data not found at {SHARED_DATA}")
    return SHARED_DATA


@pytest.fixture(scope="session")
def tiny_site(tmp_path_factory) -> Path:
    """The synthetic `tiny` site (seed 0), generated once per test session."""
    from recon_core.synthetic.generator import generate_site

    site = tmp_path_factory.mktemp("tiny") / "site"
    generate_site(site, preset="tiny", seed=0)
    return site


@pytest.fixture(scope="session")
def tiny_run(tiny_site, tmp_path_factory):
    """The full pipeline on `tiny` with the tiny preset, with every event recorded."""
    from recon_core.config import preset
    from recon_core.events import EventBus
    from recon_core.pipeline import run

    events: list = []
    out = tmp_path_factory.mktemp("tiny_out")
    state = run(tiny_site, out, preset("tiny"), bus=EventBus(events.append), resume=False)
    return state, events
