"""RPC00B fitting, projection and the GDAL/rasterio round trip (geometry only, no rendering)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from recon_core.synthetic import generator as syn
from recon_core.synthetic import rpc as R
from recon_core.synthetic.scene_model import SceneModel


def _camera(size=(1200, 1000), seed=0, index=1, off_nadir=None):
    scene = SceneModel.create(seed, 30.0, 31.2, 32.0)
    preset = syn.PRESETS["demo"]
    acq = syn.design_acquisitions(preset, seed, scene.lat0, scene.lon0)[index]
    acq.size = size
    if off_nadir is not None:
        acq.off_nadir = off_nadir
    cam = syn.make_camera(acq, scene, preset, np.random.default_rng(seed))
    return scene, cam


def _bounds(cam, h0=20.0, h1=80.0):
    foot = np.concatenate([cam.footprint(h, 10) for h in (h0, h1)])
    return (foot[:, 0].min(), foot[:, 0].max(), foot[:, 1].min(), foot[:, 1].max(), h0, h1)


def test_monomial_order():
    L, P, H = np.array([2.0]), np.array([3.0]), np.array([5.0])
    m = R.monomials(L, P, H)[0]
    expected = [1, 2, 3, 5, 6, 10, 15, 4, 9, 25, 30, 8, 18, 50, 12, 27, 75, 20, 45, 125]
    assert m.tolist() == expected


def test_fit_residual_below_005px():
    _, cam = _camera()
    b = _bounds(cam)
    model = R.fit_rpc(cam.project, b, image_size=(cam.width, cam.height))
    res = R.rpc_residuals(model, cam.project, b, image_size=(cam.width, cam.height))
    assert res["n_check"] > 1000
    assert res["max_px"] < 0.05, res
    assert res["rms_px"] < 0.02, res


def test_fit_residual_large_oblique_image():
    """A 6000 px image at 30 degrees off-nadir (strongly non-affine) still fits < 0.05 px."""
    _, cam = _camera(size=(6000, 6000), off_nadir=30.0)
    b = _bounds(cam)
    model = R.fit_rpc(cam.project, b, image_size=(cam.width, cam.height))
    res = R.rpc_residuals(model, cam.project, b, image_size=(cam.width, cam.height))
    assert res["max_px"] < 0.05, res


def test_localize_inverts_project():
    _, cam = _camera()
    b = _bounds(cam)
    model = R.fit_rpc(cam.project, b, image_size=(cam.width, cam.height))
    rng = np.random.default_rng(3)
    cr = np.stack([rng.uniform(0, cam.width - 1, 50), rng.uniform(0, cam.height - 1, 50)], -1)
    h = rng.uniform(25, 75, 50)
    llh = model.localize(cr, h)
    assert np.abs(model.project(llh) - cr).max() < 1e-5
    # and agrees with the physical camera's localization to the fit accuracy
    assert np.abs(cam.project(llh) - cr).max() < 0.05


def test_dict_round_trip():
    _, cam = _camera()
    b = _bounds(cam)
    model = R.fit_rpc(cam.project, b, image_size=(cam.width, cam.height))
    again = R.RPCModel.from_dict(model.to_dict())
    X = R.ground_grid(b, 5, 3)
    assert np.array_equal(model.project(X), again.project(X))


def test_rasterio_round_trip(tmp_path):
    rasterio = pytest.importorskip("rasterio")
    from rasterio.transform import RPCTransformer

    _, cam = _camera()
    b = _bounds(cam)
    model = R.fit_rpc(cam.project, b, image_size=(cam.width, cam.height))
    path = tmp_path / "rpc.tif"
    from rasterio.errors import NotGeoreferencedWarning

    with warnings.catch_warnings():
        warnings.simplefilter("error", NotGeoreferencedWarning)
        with rasterio.open(path, "w", driver="GTiff", width=cam.width, height=cam.height,
                           count=1, dtype="uint16", rpcs=model.to_rasterio()) as dst:
            dst.write(np.zeros((cam.height, cam.width), np.uint16), 1)
        with rasterio.open(path) as src:
            back = R.RPCModel.from_rasterio(src.rpcs)
    X = R.ground_grid(b, 12, 4, stagger=True)
    assert np.abs(back.project(X) - model.project(X)).max() < 1e-6
    # GDAL's own RPC transformer agrees, in its pixel-corner convention (+0.5 px)
    with rasterio.open(path) as src:
        tr = RPCTransformer(src.rpcs)
        rows, cols = tr.rowcol(X[:40, 0], X[:40, 1], zs=X[:40, 2], op=lambda v: v)
    ours = model.project(X[:40])
    assert np.abs(np.asarray(cols) - (ours[:, 0] + 0.5)).max() < 1e-3
    assert np.abs(np.asarray(rows) - (ours[:, 1] + 0.5)).max() < 1e-3
