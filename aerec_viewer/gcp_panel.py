"""GCP picking: the working GCP set, its file, the picking plane, and the panel.

The working set lives in OUT/gcps.geojson (SITE_FORMAT's GCP format, EPSG:4979, plus the optional
property "affine_picked": {"<group>": [x, y, z]} for positions clicked on a group's affine
cloud). It is written atomically after every change, so a crash or a closed tab loses nothing,
and it is read back when the viewer reopens the same OUT. On the first opening it starts as a
copy of the site's gcps.geojson. The site's own file is never written: it is the user's input
(and may be read-only); the pipeline can be pointed at OUT/gcps.geojson instead.

Everything a click handler does is a plain function of a `GcpSession` here (`add_observation`,
`new_gcp`, `edit_gcp`, `delete_gcp`, `set_affine_position`, `pixel_from_ray`, ...), so tests
call the same code the browser triggers. `GcpPanel` only builds widgets whose callbacks queue
those calls on the viewer's update thread.
"""

from __future__ import annotations

import copy
import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from recon_core.io_utils import atomic_path
from recon_core.site import GCP, gcps_to_geojson, read_gcps_geojson

from .display import FLAT_WXYZ, plane_hit, plane_point
from .imagery import ImageWindow

ROLES = ("control", "check")


class GcpError(ValueError):
    """A GCP edit that cannot be done (unknown id, pixel outside the image, ...)."""


@dataclass
class GcpSession:
    """The working GCP set of one OUT folder.

    Attributes:
        path: OUT/gcps.geojson, rewritten atomically after every change.
        images: image name -> (width, height) of the site's images.
        gcps: the working GCPs (recon_core.site.GCP: lon, lat, h, role, observations).
        picked: GCP id -> {group: (3,) affine position clicked on that group's cloud}.
        catalogue: the site's gcps.geojson (ground coordinates to choose from).
        version: bumped at every change (the panel and markers redraw on it).
    """

    path: Path
    images: dict[str, tuple[int, int]]
    gcps: list[GCP] = field(default_factory=list)
    picked: dict[str, dict[int, np.ndarray]] = field(default_factory=dict)
    catalogue: list[GCP] = field(default_factory=list)
    version: int = 0

    def get(self, gcp_id: str) -> GCP:
        for g in self.gcps:
            if g.id == gcp_id:
                return g
        raise GcpError(f"no GCP {gcp_id!r}")

    @property
    def ids(self) -> list[str]:
        return [g.id for g in self.gcps]


# -- file -----------------------------------------------------------------------------------
def open_session(out: str | Path, site) -> GcpSession:
    """The working set of OUT: OUT/gcps.geojson if it exists, else a copy of the site's GCPs."""
    path = Path(out) / "gcps.geojson"
    infos = {im.name: im for im in site.images}
    s = GcpSession(path, {im.name: (im.width, im.height) for im in site.images},
                   catalogue=copy.deepcopy(site.gcps))
    if path.exists():
        s.gcps = read_gcps_geojson(path, infos)
        s.picked = _read_picked(path)
    else:
        s.gcps = copy.deepcopy(site.gcps)
        save(s)
    return s


def _read_picked(path: Path) -> dict[str, dict[int, np.ndarray]]:
    doc = json.loads(Path(path).read_text())
    out: dict[str, dict[int, np.ndarray]] = {}
    for k, feat in enumerate(doc.get("features", [])):
        props = feat.get("properties") or {}
        gid = str(props.get("id", f"GCP-{k + 1:02d}"))
        for grp, xyz in (props.get("affine_picked") or {}).items():
            out.setdefault(gid, {})[int(grp)] = np.asarray(xyz, dtype=np.float64)
    return out


def save(s: GcpSession) -> None:
    """Write the working set atomically (EPSG:4979; readable by recon_core.site)."""
    doc = gcps_to_geojson(s.gcps)
    for feat in doc["features"]:
        pk = s.picked.get(feat["properties"]["id"])
        if pk:
            feat["properties"]["affine_picked"] = {str(g): [float(v) for v in xyz]
                                                   for g, xyz in sorted(pk.items())}
    doc["written_by"] = "aerec view (working GCP set; the site's gcps.geojson is left untouched)"
    with atomic_path(s.path) as tmp:
        tmp.write_text(json.dumps(doc, indent=1) + "\n")


def _changed(s: GcpSession) -> None:
    s.version += 1
    save(s)


# -- edits (what the click handlers call) -----------------------------------------------------
def next_gcp_id(s: GcpSession) -> str:
    nums = [int(m.group(1)) for g in s.gcps for m in [re.fullmatch(r"GCP-(\d+)", g.id)] if m]
    return f"GCP-{max(nums, default=0) + 1:02d}"


def ground_to_llh(x: float, y: float, h: float, epsg: int | None) -> tuple[float, float, float]:
    """(lon, lat, h) or (easting, northing, h) in a projected EPSG -> (lon, lat, h)."""
    vals = [float(v) for v in (x, y, h)]
    if not all(np.isfinite(vals)):
        raise GcpError("ground coordinates must be finite numbers")
    if epsg is None or int(epsg) in (0, 4326, 4979):
        if not (-180 <= vals[0] <= 180 and -90 <= vals[1] <= 90):
            raise GcpError(f"lon/lat {vals[0]}, {vals[1]} out of range (for E/N give an EPSG code)")
        return vals[0], vals[1], vals[2]
    from recon_core.geodesy import projected_to_geodetic

    try:
        lon, lat, hh = projected_to_geodetic(np.array(vals), int(epsg))
    except Exception as exc:
        raise GcpError(f"cannot convert from EPSG:{epsg}: {exc}") from None
    return float(lon), float(lat), float(hh)


def new_gcp(s: GcpSession, gcp_id: str | None = None, *, x: float, y: float, h: float,
            epsg: int | None = None, role: str = "control", sigma_m: float | None = None) -> GCP:
    """Add a GCP with ground coordinates (lon, lat, h, or E, N, h in `epsg`); returns it."""
    gid = (gcp_id or "").strip() or next_gcp_id(s)
    if gid in s.ids:
        raise GcpError(f"GCP {gid} already exists")
    if role not in ROLES:
        raise GcpError(f"role must be one of {ROLES}")
    lon, lat, hh = ground_to_llh(x, y, h, epsg)
    g = GCP(gid, lon, lat, hh, role, sigma_m, {})
    s.gcps.append(g)
    _changed(s)
    return g


def import_site_gcps(s: GcpSession, ids: list[str] | None = None, *,
                     with_observations: bool = True) -> list[str]:
    """Copy GCPs from the site's list (all when ids is None); ids already present are skipped."""
    added = []
    for g in s.catalogue:
        if (ids is None or g.id in ids) and g.id not in s.ids:
            c = copy.deepcopy(g)
            if not with_observations:
                c.observations = {}
            s.gcps.append(c)
            added.append(g.id)
    if added:
        _changed(s)
    return added


def edit_gcp(s: GcpSession, gcp_id: str, *, new_id: str | None = None, x: float | None = None,
             y: float | None = None, h: float | None = None, epsg: int | None = None,
             role: str | None = None) -> GCP:
    """Change a GCP's id, role or ground coordinates (x, y, h all given, or none)."""
    g = s.get(gcp_id)
    if new_id is not None and new_id.strip() and new_id.strip() != gcp_id:
        nid = new_id.strip()
        if nid in s.ids:
            raise GcpError(f"GCP {nid} already exists")
        g.id = nid
        if gcp_id in s.picked:
            s.picked[nid] = s.picked.pop(gcp_id)
    if role is not None:
        if role not in ROLES:
            raise GcpError(f"role must be one of {ROLES}")
        g.role = role
    if x is not None or y is not None or h is not None:
        if x is None or y is None or h is None:
            raise GcpError("give all three ground coordinates")
        g.lon, g.lat, g.h = ground_to_llh(x, y, h, epsg)
    _changed(s)
    return g


def delete_gcp(s: GcpSession, gcp_id: str) -> None:
    g = s.get(gcp_id)
    s.gcps.remove(g)
    s.picked.pop(gcp_id, None)
    _changed(s)


def add_observation(s: GcpSession, gcp_id: str, image: str, col: float, row: float) -> GCP:
    """Record (or replace) a GCP's observation in an image: full-image pixel (col, row)."""
    g = s.get(gcp_id)
    if image not in s.images:
        raise GcpError(f"unknown image {image!r}")
    w, h = s.images[image]
    if not (-0.5 <= col <= w - 0.5 and -0.5 <= row <= h - 0.5):
        raise GcpError(f"pixel ({col:.1f}, {row:.1f}) lies outside {image} ({w} x {h})")
    g.observations[image] = (float(col), float(row))
    _changed(s)
    return g


def remove_observation(s: GcpSession, gcp_id: str, image: str) -> None:
    g = s.get(gcp_id)
    if g.observations.pop(image, None) is None:
        raise GcpError(f"{gcp_id} has no observation in {image}")
    _changed(s)


def set_affine_position(s: GcpSession, gcp_id: str, group: int, xyz: np.ndarray | None) -> None:
    """Set (or clear, with None) a GCP's affine position picked on a group's cloud."""
    s.get(gcp_id)
    if xyz is None:
        s.picked.get(gcp_id, {}).pop(group, None)
        if not s.picked.get(gcp_id):
            s.picked.pop(gcp_id, None)
    else:
        s.picked.setdefault(gcp_id, {})[group] = np.asarray(xyz, dtype=np.float64).reshape(3)
    _changed(s)


def picked_for_group(s: GcpSession, group: int) -> dict[str, np.ndarray]:
    return {gid: d[group] for gid, d in s.picked.items() if group in d}


def describe(g: GCP, picked: dict[int, np.ndarray] | None = None) -> str:
    """Markdown description of one GCP."""
    lines = [f"**{g.id}** ({g.role}): lon {g.lon:.7f}, lat {g.lat:.7f}, h {g.h:.2f} m"]
    if g.observations:
        lines += [f"- {im}: col {c:.2f}, row {r:.2f}" for im, (c, r) in sorted(g.observations.items())]
    else:
        lines.append("- no observation yet: click its pixel on the image plane")
    for grp, xyz in sorted((picked or {}).items()):
        lines.append(f"- picked on the cloud of group {grp}")
    return "\n".join(lines)


# -- the picking plane ------------------------------------------------------------------------
@dataclass(frozen=True)
class PickPlane:
    """An image window drawn as a flat plane in the scene (display coordinates)."""

    window: ImageWindow
    position: np.ndarray
    wxyz: np.ndarray
    render_width: float
    render_height: float

    def hit(self, ray_origin, ray_direction) -> tuple[float, float] | None:
        return plane_hit(ray_origin, ray_direction, position=self.position, wxyz=self.wxyz,
                         render_width=self.render_width, render_height=self.render_height)

    def point_of(self, col: float, row: float, lift: float = 0.0) -> np.ndarray:
        """Display point of a full-image pixel on the plane (lifted above it by `lift`)."""
        fx, fy = self.window.fraction(col, row)
        return plane_point(fx, fy, position=self.position, wxyz=self.wxyz,
                           render_width=self.render_width, render_height=self.render_height,
                           lift=lift)


def pixel_from_ray(plane: PickPlane, ray_origin, ray_direction) -> tuple[float, float] | None:
    """Full-image pixel (col, row) where a click ray meets the picking plane, or None."""
    f = plane.hit(ray_origin, ray_direction)
    return None if f is None else plane.window.pixel(*f)


def layout_pick_plane(window: ImageWindow, bounds: tuple[np.ndarray, np.ndarray] | None,
                      gap: float = 0.1) -> PickPlane:
    """Place the picking plane flat, beside (east of) the displayed cloud, as tall as it (groups
    shown side by side make the cloud wider, not taller)."""
    if bounds is None:
        lo, hi = np.array([-500.0, -500.0, 0.0]), np.array([500.0, 500.0, 0.0])
    else:
        lo, hi = (np.asarray(b, dtype=np.float64) for b in bounds)
    size = float(max(hi[1] - lo[1], 1e-6))
    aspect = window.height / window.width
    w, h = (size, size * aspect) if aspect <= 1 else (size / aspect, size)
    pos = np.array([hi[0] + gap * size + w / 2, (lo[1] + hi[1]) / 2, lo[2]])
    return PickPlane(window, pos, FLAT_WXYZ.copy(), float(w), float(h))


def default_epsg(site) -> int:
    """The EPSG to offer for E, N input: site.json's crs_epsg, else the UTM zone of the GCPs."""
    if site.hints.get("crs_epsg"):
        return int(site.hints["crs_epsg"])
    if site.gcps:
        from recon_core.geodesy import utm_epsg_for

        return int(utm_epsg_for(site.gcps[0].lon, site.gcps[0].lat))
    return 32631


# -- the panel --------------------------------------------------------------------------------
class GcpPanel:
    """Widgets of the GCP tab. Callbacks queue work on the app's update thread."""

    NEW = "(new GCP from the fields below)"

    def __init__(self, app, gui):
        self.app = app
        s = app.session
        names = sorted(s.images)
        self.image = gui.add_dropdown("Image", names, initial_value=names[0])
        self.region = gui.add_dropdown("Region", ["whole image"], initial_value="whole image",
                                       hint="pick a tile to see it at full resolution")
        self.show_plane = gui.add_checkbox("Show image plane", True)
        self.goto = gui.add_button("Look at the image plane", icon=None)
        gui.add_markdown("Click a pixel on the image plane: it becomes an observation of the GCP "
                         "selected here (or of a new GCP with the fields below).")
        self.select = gui.add_dropdown("GCP", [self.NEW], initial_value=self.NEW)
        self.info = gui.add_markdown("")
        with gui.add_folder("Ground coordinates", expand_by_default=False):
            self.gid = gui.add_text("Id", "")
            self.role = gui.add_dropdown("Role", list(ROLES), initial_value="control")
            self.crs = gui.add_dropdown("Coordinates", ["lon, lat, h (WGS84)", "E, N, h (EPSG)"],
                                        initial_value="lon, lat, h (WGS84)")
            self.epsg = gui.add_number("EPSG", default_epsg(app.site), step=1,
                                       hint="projected CRS of E, N (e.g. a UTM zone)")
            self.x = gui.add_number("lon / E", 0.0, step=1e-7)
            self.y = gui.add_number("lat / N", 0.0, step=1e-7)
            self.h = gui.add_number("h (m, ellipsoidal)", 0.0, step=0.01)
            self.apply = gui.add_button("Apply to the selected GCP")
            self.create = gui.add_button("New GCP")
        with gui.add_folder("Site GCP list", expand_by_default=False):
            cat = [g.id for g in s.catalogue] or ["(the site has no gcps.geojson)"]
            self.catalogue = gui.add_dropdown("Site GCP", cat, initial_value=cat[0])
            self.take = gui.add_button("Add it (ground coordinates only)")
            self.take_all = gui.add_button("Add all site GCPs with their observations")
        self.pick_cloud = gui.add_button("Pick its position on the cloud (next click)")
        self.unobserve = gui.add_button("Remove its observation in this image")
        self.delete = gui.add_button("Delete the selected GCP", color="red")
        self.status = gui.add_markdown("")
        self._wire()

    def _wire(self) -> None:
        app = self.app
        self.image.on_update(lambda _: app.submit(self.app.show_image_plane))
        self.region.on_update(lambda _: app.submit(self.app.show_image_plane))
        self.show_plane.on_update(lambda _: app.submit(self.app.show_image_plane))
        self.goto.on_click(lambda ev: app.submit(lambda: self.app.look_at_plane(ev.client)))
        self.select.on_update(lambda _: app.submit(self.fill_fields))
        self.crs.on_update(lambda _: app.submit(self._convert_fields))
        self.apply.on_click(lambda _: app.submit(self._apply))
        self.create.on_click(lambda _: app.submit(self._create))
        self.take.on_click(lambda _: app.submit(self._take))
        self.take_all.on_click(lambda _: app.submit(self._take_all))
        self.pick_cloud.on_click(lambda _: app.submit(self.app.arm_cloud_pick))
        self.unobserve.on_click(lambda _: app.submit(self._unobserve))
        self.delete.on_click(lambda _: app.submit(self._delete))

    # -- actions (update thread) ----------------------------------------------------------------
    def selected(self) -> str | None:
        v = self.select.value
        return None if v == self.NEW else v

    def _ground(self) -> tuple[float, float, float, int | None]:
        epsg = int(self.epsg.value) if self.crs.value.startswith("E") else None
        return float(self.x.value), float(self.y.value), float(self.h.value), epsg

    def _convert_fields(self) -> None:
        """Switching between lon/lat and E/N converts the typed coordinates."""
        from recon_core.geodesy import geodetic_to_projected

        x, y, h = float(self.x.value), float(self.y.value), float(self.h.value)
        if x == 0.0 and y == 0.0:
            return
        epsg = int(self.epsg.value)
        if self.crs.value.startswith("E"):
            if -180 <= x <= 180 and -90 <= y <= 90:
                e, n, _ = geodetic_to_projected(np.array([x, y, h]), epsg)
                self.x.value, self.y.value = round(float(e), 3), round(float(n), 3)
        elif abs(x) > 180 or abs(y) > 90:
            lon, lat, _ = ground_to_llh(x, y, h, epsg)
            self.x.value, self.y.value = lon, lat

    def _apply(self) -> None:
        gid = self.selected()
        if gid is None:
            raise GcpError("select a GCP first (or press New GCP)")
        x, y, h, epsg = self._ground()
        g = edit_gcp(self.app.session, gid, new_id=self.gid.value, x=x, y=y, h=h, epsg=epsg,
                     role=self.role.value)
        self.app.gcps_changed(select=g.id, note=f"{g.id} updated")

    def _create(self) -> None:
        x, y, h, epsg = self._ground()
        g = new_gcp(self.app.session, self.gid.value or None, x=x, y=y, h=h, epsg=epsg,
                    role=self.role.value)
        self.app.gcps_changed(select=g.id, note=f"{g.id} created: now click its pixel")

    def _take(self) -> None:
        added = import_site_gcps(self.app.session, [self.catalogue.value], with_observations=False)
        self.app.gcps_changed(select=added[0] if added else self.catalogue.value,
                              note=f"added {added[0]}: click its pixel in each image" if added
                              else f"{self.catalogue.value} is already in the working set")

    def _take_all(self) -> None:
        added = import_site_gcps(self.app.session, None, with_observations=True)
        self.app.gcps_changed(note=f"added {len(added)} site GCP(s)")

    def _unobserve(self) -> None:
        gid = self.selected()
        if gid is None:
            raise GcpError("select a GCP first")
        remove_observation(self.app.session, gid, self.image.value)
        self.app.gcps_changed(select=gid, note=f"removed {gid}'s observation in {self.image.value}")

    def _delete(self) -> None:
        gid = self.selected()
        if gid is None:
            raise GcpError("select a GCP first")
        delete_gcp(self.app.session, gid)
        self.app.gcps_changed(select=None, note=f"deleted {gid}")

    # -- display --------------------------------------------------------------------------------
    def refresh(self, select: str | None = "keep") -> None:
        s = self.app.session
        options = [self.NEW] + s.ids
        current = self.select.value if select == "keep" else (select or self.NEW)
        if current not in options:
            current = self.NEW
        if tuple(self.select.options) != tuple(options):
            self.select.options = options
        if self.select.value != current:
            self.select.value = current
        self.fill_fields()

    def fill_fields(self) -> None:
        gid = self.selected()
        s = self.app.session
        if gid is None or gid not in s.ids:
            self.info.content = (f"{len(s.gcps)} GCP(s) in the working set "
                                 f"(`{s.path.name}` in the output folder)")
            self.gid.value = ""
            return
        g = s.get(gid)
        self.info.content = describe(g, s.picked.get(gid))
        self.gid.value = g.id
        self.role.value = g.role
        self.crs.value = "lon, lat, h (WGS84)"
        self.x.value, self.y.value, self.h.value = g.lon, g.lat, g.h

    def set_regions(self, names: list[str]) -> None:
        opts = ["whole image"] + names
        if tuple(self.region.options) != tuple(opts):
            self.region.options = opts
            self.region.value = "whole image"
