"""GCP files: the site format's gcps.geojson, read and written here only, and the working set.

Besides the site's own gcps.geojson there is a *working set*, OUT/gcps.geojson: the viewer's
edits (clicked observations, roles, new points, positions picked on a group's affine cloud in
the optional property "affine_picked": {"<group>": [x, y, z]}). A run uses the working set when
it exists, the site's file otherwise (`working_gcp_file`); the site's file is never written.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Protocol

import numpy as np

from recon_core.errors import InputError
from recon_core.geometry.geodesy import projected_to_geodetic
from recon_core.io.checks import finite_number, projected_epsg
from recon_core.io.files import atomic_path


@dataclass
class GCP:
    """A ground control point: geodetic position (lon, lat, h) and its image observations."""

    id: str
    lon: float
    lat: float
    h: float
    role: str = "control"
    sigma_m: float | None = None
    observations: dict[str, tuple[float, float]] = field(default_factory=dict)
    # positions picked on a group's affine cloud (the viewer): group -> (3,) affine point; they
    # take the place of triangulating the observations in that group
    affine_picked: dict[int, np.ndarray] = field(default_factory=dict)
    # False: kept in the file (and shown) but left out of the fit and of the scores, with that
    # reason in the report (optional property "enabled", written only when false)
    enabled: bool = True
    # the height's own standard deviation (m) when it is known worse than the horizontal: a
    # height read off a DEM at a roof's edge (optional property "sigma_h_m")
    sigma_h_m: float | None = None

    @property
    def llh(self) -> np.ndarray:
        return np.array([self.lon, self.lat, self.h])


MAX_ABS_HEIGHT_M = 12_000.0      # ellipsoidal heights of the Earth's surface lie within this


class ImageSize(Protocol):
    """What an observation is checked against: its image's size (an ImageInfo, or its size)."""

    @property
    def width(self) -> int: ...
    @property
    def height(self) -> int: ...


def read_gcps_geojson(path: Path, images: Mapping[str, ImageSize] | None = None) -> list[GCP]:
    """Read GCPs; coordinates converted to geodetic (lon, lat, h). Validates observations."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "is not a file" if path.exists() else "does not exist")
    try:
        doc = json.loads(path.read_text())
    except (ValueError, UnicodeDecodeError) as exc:
        raise InputError(path, f"malformed GeoJSON ({exc})") from None
    if not isinstance(doc, dict) or doc.get("type") != "FeatureCollection" \
            or not isinstance(doc.get("features"), list):
        raise InputError(path, "malformed GeoJSON: expected a FeatureCollection with a features list")
    epsg = doc.get("crs_epsg")
    if epsg is not None:
        epsg = projected_epsg(epsg, path, "crs_epsg")
    gcps: list[GCP] = []
    for k, feat in enumerate(doc["features"]):
        gcps.append(_parse_feature(path, k, feat, epsg, images))
    if epsg is not None and gcps:            # projected x, y: converted in one call
        llh = projected_to_geodetic(np.array([[g.lon, g.lat, g.h] for g in gcps], float), int(epsg))
        for g, (lon, lat, h) in zip(gcps, llh):
            if not (np.isfinite(lon) and np.isfinite(lat) and -180 <= lon <= 180 and -90 <= lat <= 90):
                raise InputError(path, f"GCP {g.id}: x, y {g.lon:g}, {g.lat:g} are not a place of "
                                       f"EPSG:{epsg} on Earth")
            g.lon, g.lat, g.h = float(lon), float(lat), float(h)
    seen, dup = set(), set()
    for g in gcps:
        (dup if g.id in seen else seen).add(g.id)
    if dup:
        raise InputError(path, f"duplicate GCP ids {sorted(dup)[:10]}" + (" ..." if len(dup) > 10 else ""))
    return gcps


def _parse_feature(path: Path, k: int, feat, epsg, images) -> GCP:
    where = f"feature {k}"
    try:
        geom, props = feat["geometry"], feat.get("properties") or {}
        if not isinstance(props, dict):
            raise InputError(path, f"{where}: properties must be a JSON object, not {type(props).__name__}")
        if geom.get("type") != "Point":
            raise InputError(path, f"{where}: geometry must be a Point")
        coords = geom["coordinates"]
    except (TypeError, KeyError, AttributeError):
        raise InputError(path, f"malformed GeoJSON: {where} has no Point geometry") from None
    if not (isinstance(coords, list) and len(coords) == 3 and all(finite_number(c) for c in coords)):
        raise InputError(path, f"{where}: coordinates must be [lon, lat, h] (3 numbers)")
    gid = str(props.get("id", f"GCP-{k + 1:02d}"))
    where = f"GCP {gid}"
    lon, lat, h = (float(c) for c in coords)           # projected x, y: converted by the caller
    if epsg is None and not (-180 <= lon <= 180 and -90 <= lat <= 90):
        raise InputError(path, f"{where}: lon/lat {lon}, {lat} out of range")
    if not -MAX_ABS_HEIGHT_M <= h <= MAX_ABS_HEIGHT_M:
        raise InputError(path, f"{where}: ellipsoidal height {h:g} m is not on the Earth's surface "
                               f"(|h| <= {MAX_ABS_HEIGHT_M:g} m)")
    role = props.get("role", "control")
    if role not in ("control", "check"):
        raise InputError(path, f"{where}: role must be 'control' or 'check', not {role!r}")
    obs_in = props.get("observations", {})
    if not isinstance(obs_in, dict):
        raise InputError(path, f"{where}: observations must map image names to [col, row]")
    obs: dict[str, tuple[float, float]] = {}
    for name, xy in obs_in.items():
        if not (isinstance(xy, list) and len(xy) == 2 and all(finite_number(v) for v in xy)):
            raise InputError(path, f"{where}: observation in {name} must be [col, row]")
        if images is not None:
            check_observation(path, where, name, xy, images)
        obs[name] = (float(xy[0]), float(xy[1]))
    sigma = props.get("sigma_m")
    if sigma is not None and not (finite_number(sigma) and sigma > 0):
        raise InputError(path, f"{where}: sigma_m must be a positive number of metres, not {sigma!r}")
    sigma_h = props.get("sigma_h_m")
    if sigma_h is not None and not (finite_number(sigma_h) and sigma_h > 0):
        raise InputError(path, f"{where}: sigma_h_m must be a positive number of metres, not {sigma_h!r}")
    enabled = props.get("enabled", True)
    if not isinstance(enabled, bool):
        raise InputError(path, f"{where}: enabled must be true or false, not {enabled!r}")
    return GCP(id=gid, lon=lon, lat=lat, h=h, role=role,
               sigma_m=None if sigma is None else float(sigma),
               sigma_h_m=None if sigma_h is None else float(sigma_h), observations=obs,
               affine_picked=_parse_picked(path, where, props.get("affine_picked")),
               enabled=enabled)


def check_observation(path: Path, where: str, name: str, xy, images: dict) -> None:
    """An observation must name a site image and lie inside it (pixel-centre convention)."""
    if name not in images:
        raise InputError(path, f"{where}: observation refers to unknown image {name!r}")
    im = images[name]
    if not (-0.5 <= xy[0] <= im.width - 0.5 and -0.5 <= xy[1] <= im.height - 0.5):
        raise InputError(path, f"{where}: observation {list(xy)} lies outside {name} "
                               f"({im.width} x {im.height} px)")


def _parse_picked(path: Path, where: str, picked) -> dict[int, np.ndarray]:
    """The optional "affine_picked": {"<group>": [x, y, z]} property."""
    if picked is None:
        return {}
    if not isinstance(picked, dict):
        raise InputError(path, f"{where}: affine_picked must map a group index to [x, y, z]")
    out = {}
    for grp, xyz in picked.items():
        if not (str(grp).isdigit() and isinstance(xyz, list) and len(xyz) == 3
                and all(finite_number(v) for v in xyz)):
            raise InputError(path, f"{where}: affine_picked[{grp!r}] must be [x, y, z] for a group index")
        out[int(grp)] = np.array(xyz, dtype=np.float64)
    return out


def gcps_to_geojson(gcps: list[GCP]) -> dict:
    feats = []
    for g in gcps:
        props = {"id": g.id, "role": g.role,
                 "observations": {k: [round(v[0], 4), round(v[1], 4)] for k, v in g.observations.items()}}
        if g.sigma_m is not None:
            props["sigma_m"] = g.sigma_m
        if g.sigma_h_m is not None:
            props["sigma_h_m"] = g.sigma_h_m
        if not g.enabled:
            props["enabled"] = False
        if g.affine_picked:
            props["affine_picked"] = {str(k): [float(v) for v in xyz]
                                      for k, xyz in sorted(g.affine_picked.items())}
        feats.append({"type": "Feature",
                      "geometry": {"type": "Point",
                                   "coordinates": [round(g.lon, 10), round(g.lat, 10), round(g.h, 4)]},
                      "properties": props})
    return {"type": "FeatureCollection", "features": feats}


def write_gcps_geojson(path: str | Path, gcps: list[GCP], **top: object) -> None:
    """Write GCPs atomically in EPSG:4979 (lon, lat, ellipsoidal h); `top` adds top-level members."""
    doc = gcps_to_geojson(gcps) | top
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(doc, indent=1) + "\n")


def working_gcp_file(site_root: str | Path, out: str | Path) -> Path:
    """The GCP file a run on OUT uses: OUT/gcps.geojson (the working set) when it exists, else
    the site's own gcps.geojson."""
    own = Path(out) / "gcps.geojson"
    return own if own.exists() else Path(site_root) / "gcps.geojson"


def picked_positions(gcps: list[GCP], group: int) -> dict[str, np.ndarray]:
    """GCP id -> affine position picked on `group`'s cloud, for the GCPs that have one."""
    return {g.id: g.affine_picked[group] for g in gcps if group in g.affine_picked}
