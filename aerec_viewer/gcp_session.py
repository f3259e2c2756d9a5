"""The working GCP set of one output folder and every edit of it, with no widget in sight.

The working set lives in OUT/gcps.geojson (recon_core.io.gcps reads and writes it, including the
optional "affine_picked" positions). It is written atomically after every change, so a crash or
a closed tab loses nothing, and it is read back when the viewer reopens the same OUT. On the
first opening it starts as a copy of the site's gcps.geojson. The site's own file is never
written: it is the user's input (and may be read-only); a run on OUT uses the working set.

Everything a click handler does is a plain function of a `GcpSession` here (`add_observation`,
`new_gcp`, `edit_gcp`, `delete_gcp`, `set_affine_position`, ...), so tests call the same code
the browser triggers.
"""

from __future__ import annotations

import copy
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from recon_core.io.gcps import GCP, read_gcps_geojson, write_gcps_geojson
from recon_core.io.layout import OutLayout

ROLES = ("control", "check")


class GcpError(ValueError):
    """A GCP edit that cannot be done (unknown id, pixel outside the image, ...)."""


@dataclass
class GcpSession:
    """The working GCP set of one OUT folder.

    Attributes:
        path: OUT/gcps.geojson, rewritten atomically after every change.
        images: image name -> (width, height) of the site's images.
        gcps: the working GCPs (recon_core.io.site.GCP: lon, lat, h, role, observations).
        picked: GCP id -> {group: (3,) affine position clicked on that group's cloud}.
        catalogue: the site's gcps.geojson (ground coordinates to choose from).
        version: bumped at every change (the panel and markers redraw on it).
    """

    path: Path
    images: dict[str, tuple[int, int]]
    gcps: list[GCP] = field(default_factory=list)
    catalogue: list[GCP] = field(default_factory=list)
    version: int = 0
    history_limit: int = 200
    _undo: list = field(default_factory=list, repr=False)    # (gcps before, what) per edit
    _redo: list = field(default_factory=list, repr=False)
    _last: list | None = field(default=None, repr=False)     # gcps after the latest edit

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
    path = OutLayout(out).gcps
    infos = {im.name: im for im in site.images}
    s = GcpSession(path, {im.name: (im.width, im.height) for im in site.images},
                   catalogue=copy.deepcopy(site.gcps))
    if path.exists():
        s.gcps = read_gcps_geojson(path, infos)
    else:
        s.gcps = copy.deepcopy(site.gcps)
        save(s)
    s._last = copy.deepcopy(s.gcps)
    return s


def save(s: GcpSession) -> None:
    """Write the working set atomically (recon_core.io.gcps: what the run reads back)."""
    write_gcps_geojson(s.path, s.gcps, written_by="aerec view (working GCP set; the site's "
                                                  "gcps.geojson is left untouched)")


def _changed(s: GcpSession, what: str = "edit") -> None:
    """Record an edit: the state before it goes on the undo stack (the redo stack empties)."""
    if s._last is not None:
        s._undo.append((s._last, what))
        del s._undo[:-s.history_limit]
    s._redo.clear()
    s._last = copy.deepcopy(s.gcps)
    s.version += 1
    save(s)


def can_undo(s: GcpSession) -> str | None:
    """What Undo would revert (None: nothing)."""
    return s._undo[-1][1] if s._undo else None


def can_redo(s: GcpSession) -> str | None:
    return s._redo[-1][1] if s._redo else None


def _restore(s: GcpSession, src: list, dst: list, verb: str) -> str:
    if not src:
        raise GcpError(f"nothing to {verb}")
    state, what = src.pop()
    dst.append((s._last if s._last is not None else copy.deepcopy(s.gcps), what))
    s.gcps = copy.deepcopy(state)
    s._last = copy.deepcopy(state)
    s.version += 1
    save(s)
    return what


def merge_last(s: GcpSession, n: int, what: str) -> None:
    """Make the last n edits one step of the history (one Undo reverts them all)."""
    if n < 2 or len(s._undo) < n:
        return
    first_state = s._undo[-n][0]
    del s._undo[-n:]
    s._undo.append((first_state, what))


def undo(s: GcpSession) -> str:
    """Revert the latest edit (any kind: observation, ground coordinates, role, delete, ...);
    returns what was undone."""
    return _restore(s, s._undo, s._redo, "undo")


def redo(s: GcpSession) -> str:
    """Re-apply the latest undone edit; returns what was redone."""
    return _restore(s, s._redo, s._undo, "redo")


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
    from recon_core.geometry.geodesy import projected_to_geodetic

    try:
        lon, lat, hh = projected_to_geodetic(np.array(vals), int(epsg))
    except Exception as exc:
        raise GcpError(f"cannot convert from EPSG:{epsg}: {exc}") from None
    return float(lon), float(lat), float(hh)


def new_gcp(s: GcpSession, gcp_id: str | None = None, *, x: float, y: float, h: float,
            epsg: int | None = None, role: str = "control", sigma_m: float | None = None,
            sigma_h_m: float | None = None) -> GCP:
    """Add a GCP with ground coordinates (lon, lat, h, or E, N, h in `epsg`; sigma_h_m: its
    height known only to that many metres); returns it."""
    gid = (gcp_id or "").strip() or next_gcp_id(s)
    if gid in s.ids:
        raise GcpError(f"GCP {gid} already exists")
    if role not in ROLES:
        raise GcpError(f"role must be one of {ROLES}")
    lon, lat, hh = ground_to_llh(x, y, h, epsg)
    for other in s.gcps:
        if abs(other.lon - lon) < 1e-9 and abs(other.lat - lat) < 1e-9 and abs(other.h - hh) < 1e-4:
            raise GcpError(f"{other.id} already has these ground coordinates: type the new GCP's "
                           f"own coordinates (or select {other.id} to add an observation to it)")
    g = GCP(gid, lon, lat, hh, role, sigma_m, {}, sigma_h_m=sigma_h_m)
    s.gcps.append(g)
    _changed(s, f"new {gid}")
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
        _changed(s, f"add {', '.join(added)} from the site list")
    return added


def merge_gcps(s: GcpSession, gcps: list[GCP], source: str = "CSV") -> tuple[list[str], list[str]]:
    """Bring GCPs (a marker file) into the working set, as one step of the history: a new id is
    added; a known one takes the file's ground position, role and sigmas, and its observations
    (the others it had are kept). Every observation is checked first (image of the site, pixel
    inside it): nothing changes unless all are. Returns (ids added, ids updated)."""
    bad = []
    for g in gcps:
        for im, (c, r) in g.observations.items():
            if im not in s.images:
                bad.append(f"{g.id}: no image {im!r} in the site")
            elif not (-0.5 <= c <= s.images[im][0] - 0.5 and -0.5 <= r <= s.images[im][1] - 0.5):
                bad.append(f"{g.id}: pixel ({c:.1f}, {r:.1f}) outside {im}")
    if bad:
        raise GcpError(f"{source}: nothing imported: " + "; ".join(bad[:5]) + (f" (and {len(bad) - 5} more)" if len(bad) > 5 else ""))
    added, updated = [], []
    for g in gcps:
        if g.id in s.ids:
            have = s.get(g.id)
            have.lon, have.lat, have.h, have.role = g.lon, g.lat, g.h, g.role
            have.sigma_m, have.sigma_h_m = g.sigma_m, g.sigma_h_m
            have.observations.update(g.observations)
            updated.append(g.id)
        else:
            s.gcps.append(copy.deepcopy(g))
            added.append(g.id)
    if added or updated:
        _changed(s, f"import {len(added) + len(updated)} GCP(s) from {source}")
    return added, updated


def edit_gcp(s: GcpSession, gcp_id: str, *, new_id: str | None = None, x: float | None = None,
             y: float | None = None, h: float | None = None, epsg: int | None = None,
             role: str | None = None, sigma_h_m: float | None | Literal["typed"] = "typed") -> GCP:
    """Change a GCP's id, role or ground coordinates (x, y, h all given, or none). sigma_h_m:
    how well the new height is known (metres; None: as the horizontal); "typed" (the default):
    a height typed in is the operator's (as well known as the rest), an unchanged one keeps its
    sigma."""
    g = s.get(gcp_id)
    nid = new_id.strip() if new_id is not None and new_id.strip() and new_id.strip() != gcp_id else None
    if nid is not None and nid in s.ids:
        raise GcpError(f"GCP {nid} already exists")
    if role is not None and role not in ROLES:
        raise GcpError(f"role must be one of {ROLES}")
    llh = None
    if x is not None or y is not None or h is not None:
        if x is None or y is None or h is None:
            raise GcpError("give all three ground coordinates")
        llh = ground_to_llh(x, y, h, epsg)
    # validated: now change (an edit either happens whole or not at all)
    if nid is not None:
        g.id = nid
    if role is not None:
        g.role = role
    if llh is not None:
        if sigma_h_m != "typed":
            g.sigma_h_m = sigma_h_m
        elif abs(llh[2] - g.h) > 1e-4:
            g.sigma_h_m = None
        g.lon, g.lat, g.h = llh
    _changed(s, f"edit {g.id}")
    return g


def set_enabled(s: GcpSession, gcp_id: str, enabled: bool) -> GCP:
    """Enable or disable a GCP: a disabled one stays in the working set (with its observations)
    but the upgrade leaves it out of the fit and the scores ("enabled": false in the file)."""
    g = s.get(gcp_id)
    if g.enabled == bool(enabled):
        raise GcpError(f"{gcp_id} is already {'enabled' if enabled else 'disabled'}")
    g.enabled = bool(enabled)
    _changed(s, f"{'enable' if enabled else 'disable'} {gcp_id}")
    return g


def toggle_role(s: GcpSession, gcp_id: str) -> GCP:
    """Control <-> check."""
    g = s.get(gcp_id)
    return edit_gcp(s, gcp_id, role="check" if g.role == "control" else "control")


def delete_gcp(s: GcpSession, gcp_id: str) -> None:
    g = s.get(gcp_id)
    s.gcps.remove(g)
    _changed(s, f"delete {gcp_id}")


def add_observation(s: GcpSession, gcp_id: str, image: str, col: float, row: float,
                    what: str | None = None) -> GCP:
    """Record (or replace) a GCP's observation in an image: full-image pixel (col, row); `what`
    names the edit in the history (default: add or move)."""
    g = s.get(gcp_id)
    if image not in s.images:
        raise GcpError(f"unknown image {image!r}")
    w, h = s.images[image]
    if not (-0.5 <= col <= w - 0.5 and -0.5 <= row <= h - 0.5):
        raise GcpError(f"pixel ({col:.1f}, {row:.1f}) lies outside {image} ({w} x {h})")
    had = image in g.observations
    g.observations[image] = (float(col), float(row))
    _changed(s, what or f"{'move' if had else 'add'} {gcp_id}'s observation in {image}")
    return g


def nudge_observation(s: GcpSession, gcp_id: str, image: str, dcol: float, drow: float) -> tuple[float, float]:
    """Move a GCP's observation in an image by (dcol, drow) pixels; successive nudges of the same
    observation are one step of the history. Returns the new (col, row)."""
    g = s.get(gcp_id)
    if image not in g.observations:
        raise GcpError(f"{gcp_id} has no observation in {image} to nudge: click its pixel first")
    c, r = g.observations[image]
    what = f"nudge {gcp_id}'s observation in {image}"
    again = bool(s._undo) and s._undo[-1][1] == what and not s._redo
    add_observation(s, gcp_id, image, c + dcol, r + drow, what=what)
    if again:
        merge_last(s, 2, what)
    return g.observations[image]


def remove_observation(s: GcpSession, gcp_id: str, image: str) -> None:
    g = s.get(gcp_id)
    if g.observations.pop(image, None) is None:
        raise GcpError(f"{gcp_id} has no observation in {image}")
    _changed(s, f"remove {gcp_id}'s observation in {image}")


def set_affine_position(s: GcpSession, gcp_id: str, group: int, xyz: np.ndarray | None) -> None:
    """Set (or clear, with None) a GCP's affine position picked on a group's cloud."""
    g = s.get(gcp_id)
    if xyz is None:
        if g.affine_picked.pop(group, None) is None:
            raise GcpError(f"{gcp_id} has no position picked on the cloud of group {group}")
        _changed(s, f"forget {gcp_id}'s cloud pick in group {group}")
    else:
        g.affine_picked[group] = np.asarray(xyz, dtype=np.float64).reshape(3)
        _changed(s, f"pick {gcp_id} on the cloud of group {group}")


# an observation whose reprojection residual exceeds this is flagged (as its red residual vector)
FLAG_RESIDUAL_PX = 1.0


def describe(g: GCP, residuals: dict[str, float] | None = None) -> str:
    """Markdown description of one GCP; `residuals`: image -> reprojection residual (px) of
    its observations (where it is triangulated), shown and flagged above FLAG_RESIDUAL_PX."""
    lines = [f"**{g.id}** ({g.role}{'' if g.enabled else ', **disabled**: left out of the upgrade'}): "
             f"lon {g.lon:.7f}, lat {g.lat:.7f}, h {g.h:.2f} m"
             + (f" **+- {g.sigma_h_m:.1f} m**" if g.sigma_h_m is not None else "")]
    if g.sigma_h_m is not None:
        lines.append(f"- *its height is known only to +- {g.sigma_h_m:.1f} m* (read off the DEM where it "
                     "changes around the spot: a roof or a wall?). The upgrade takes its height from the "
                     "images where they know their viewing angles; after it, \"Take the images' height\" "
                     "sets it. Or type the surveyed height.")
    res = residuals or {}

    def tail(im: str) -> str:
        if im not in res:
            return ""
        r = res[im]
        return f", residual **{r:.2f} px: check it**" if r > FLAG_RESIDUAL_PX else f", residual {r:.2f} px"
    if g.observations:
        lines += [f"- {im}: col {c:.2f}, row {r:.2f}{tail(im)}" for im, (c, r) in sorted(g.observations.items())]
    else:
        lines.append("- no observation yet: click its pixel on the image plane")
    for grp in sorted(g.affine_picked):
        lines.append(f"- picked on the cloud of group {grp}: this position replaces the image "
                     f"observations in that group (\"Forget its cloud pick\" removes it)")
    return "\n".join(lines)


def default_epsg(site) -> int:
    """The EPSG to offer for E, N input: site.json's crs_epsg, else the UTM zone of the GCPs."""
    if site.hints.get("crs_epsg"):
        return int(site.hints["crs_epsg"])
    if site.gcps:
        from recon_core.geometry.geodesy import utm_epsg_for

        return int(utm_epsg_for(site.gcps[0].lon, site.gcps[0].lat))
    return 32631
