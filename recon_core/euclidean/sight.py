"""Each image's line of sight, in the affine frame and, from its metadata, on the ground.

A pushbroom camera images the whole line of sight through a ground point at one pixel: every
point of it is on the view plane of the same instant, in the same direction from the satellite.
So the affine camera of a tile, x = M X + t, maps the line of sight to one pixel: its direction
in the affine frame is the null vector of M (M's two rows crossed). The vendor's metadata gives
the same direction on the ground, at the image centre: incidence from the local vertical and
azimuth (the site format's sidecar member `view`). The upgrade's linear part A must map the one
onto the other, A d ~ v: two equations per image on the height scale and the shear of height
into easting and northing, exactly what GCPs on flat ground leave loose (recon_core.euclidean.
held).

The affine direction is taken at the image centre, as the metadata states it: a plane fitted to
the unit null vectors of the image's registered tiles, against their centres, read at the
centre pixel (the line of sight turns across the swath and along the scan). The ground
direction is given in the local vertical of the image centre's ground point; it is turned into
the site's ENU frame there, since the vertical turns by 1.6e-4 rad per kilometre.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from recon_core.geometry.affine import apply_affine_3d
from recon_core.geometry.geodesy import LocalFrame, enu_rotation
from recon_core.model.images import ViewAngles


@dataclass(frozen=True)
class ViewRay:
    """One image's line of sight at its centre: `d` the unit direction in the affine frame (either
    sign), `v_local` the unit direction to the satellite in the ENU frame of the image centre's
    ground point, `centre` an affine point on the ground near the image centre (where that frame
    is taken), `tiles` how many tile cameras gave d."""

    image: str
    d: np.ndarray
    v_local: np.ndarray
    centre: np.ndarray
    tiles: int

    def direction(self, frame: LocalFrame | None = None, H: np.ndarray | None = None) -> np.ndarray:
        """The direction to the satellite in the site's ENU frame: v_local turned from the
        image centre's vertical (its ground point through H) into the frame's (no turn without
        both)."""
        if frame is None or H is None:
            return self.v_local
        lon, lat = frame.enu_to_geodetic(apply_affine_3d(H, self.centre[None]))[0, :2]
        return frame.R @ enu_rotation(float(lon), float(lat)).T @ self.v_local


def view_direction(view: ViewAngles) -> np.ndarray:
    """(3,) unit ENU direction from the ground to the satellite: incidence from the vertical,
    azimuth clockwise from north."""
    th, az = np.radians(view.incidence_deg), np.radians(view.azimuth_deg)
    return np.array([np.sin(th) * np.sin(az), np.sin(th) * np.cos(az), np.cos(th)])


def tile_sight(M: np.ndarray) -> np.ndarray:
    """(3,) the unit null vector of an affine camera's linear part M (2 x 3)."""
    d = np.cross(M[0], M[1])
    return d / max(float(np.linalg.norm(d)), 1e-300)


def lines_of_sight(model, images: dict) -> list[ViewRay]:
    """The lines of sight of the model's images whose metadata states a view.

    Args:
        model: a SparseModel (or the joint model of several date groups).
        images: image name -> ImageInfo (its size and `view`); images without a view, or without
            a registered tile, give no ray.
    """
    rays = []
    reg = np.flatnonzero(model.registered)
    for name in model.images:
        info = images.get(name)
        if info is None or info.view is None:
            continue
        tiles = [t for t in reg if model.tiles[t].image == name]
        if not tiles:
            continue
        D = np.array([tile_sight(np.asarray(model.cams[t], np.float64)[:, :3]) for t in tiles])
        D *= np.sign(D @ D[0])[:, None]
        C = np.array([(model.tiles[t].col0 + model.tiles[t].width / 2.0,
                       model.tiles[t].row0 + model.tiles[t].height / 2.0) for t in tiles])
        centre_px = np.array([(info.width - 1) / 2.0, (info.height - 1) / 2.0])
        if len(tiles) >= 3 and np.linalg.matrix_rank(C - C.mean(0), tol=1.0) == 2:
            scale = max(float(np.abs(C - centre_px).max()), 1.0)
            B = np.c_[np.ones(len(C)), (C - centre_px) / scale]
            d = np.linalg.lstsq(B, D, rcond=None)[0][0]
        else:
            d = D.mean(axis=0)
        near = tiles[int(np.argmin(np.linalg.norm(C - centre_px, axis=1)))]
        rays.append(ViewRay(name, d / np.linalg.norm(d), view_direction(info.view),
                            _ground_near(model, near), len(tiles)))
    return rays


def _ground_near(model, tile: int | np.integer) -> np.ndarray:
    """(3,) the mean affine position of the points a tile observes (the model's centre if none)."""
    o = model.obs
    k = np.flatnonzero((o.tile == tile) & o.valid & model.has_point[o.track])
    pts = model.X[o.track[k]] if len(k) else model.X[model.has_point]
    return pts.mean(axis=0) if len(pts) else np.zeros(3)
