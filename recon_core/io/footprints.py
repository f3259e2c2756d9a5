"""Where a site's images lie on the ground, from their RPCs: for the checks of the GCPs and of
reference files only (the reconstruction never reads an RPC: that is the method's point)."""

from __future__ import annotations

import warnings

import numpy as np


def image_footprints(site) -> list[tuple[str, np.ndarray]]:
    """(image name, (4, 2) lon, lat of its corners) of the images with RPCs, localised at their
    RPC's height offset: where the site is, for the checks of the GCPs and reference files only
    (the reconstruction never reads an RPC)."""
    import rasterio

    from recon_core.geometry.rpc import RPCModel

    out = []
    for im in site.images:
        if not im.has_rpc:
            continue
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                with rasterio.open(im.path) as ds:
                    rpc = RPCModel.from_rasterio(ds.rpcs)
            cr = np.array([[0, 0], [im.width - 1, 0], [im.width - 1, im.height - 1], [0, im.height - 1]], float)
            ll = rpc.localize(cr, rpc.height_off)[:, :2]
        except Exception:                  # an RPC that does not localise: no footprint from it
            continue
        if np.all(np.isfinite(ll)) and np.all(np.abs(ll[:, 1]) <= 90):
            out.append((im.name, ll))
    return out


def off_the_images(lonlat: np.ndarray, footprints: list[tuple[str, np.ndarray]]) -> np.ndarray:
    """(n,) metres from each lon, lat to the nearest image footprint's bounding box (0 inside)."""
    from recon_core.geometry.geodesy import LocalFrame

    allc = np.concatenate([ll for _, ll in footprints])
    frame = LocalFrame(float(np.mean(allc[:, 0])), float(np.mean(allc[:, 1])))

    def en(ll):
        return frame.geodetic_to_enu(np.c_[ll, np.zeros(len(ll))])[:, :2]
    pts = en(np.asarray(lonlat, float).reshape(-1, 2))
    d = np.full(len(pts), np.inf)
    for _, ll in footprints:
        b = en(ll)
        lo, hi = b.min(0), b.max(0)
        gap = np.maximum(np.maximum(lo - pts, pts - hi), 0.0)
        d = np.minimum(d, np.hypot(gap[:, 0], gap[:, 1]))
    return d
