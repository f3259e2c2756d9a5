"""The GCP controller: what a click on the picking plane, the reference orthoimage or the cloud
records, every edit's consequences (the markers, the lists, the Upgrade button), and the upgrade
the Results tab runs. It owns the working set's edits; the viewer (app.ViewerApp) keeps the
lifecycle, the update loop and the frames, and the GCP tab (gcp_panel) its widgets.
Every method runs on the viewer's update thread, like every scene change.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from recon_core.context import UpgradeMaps
from recon_core.errors import AerecError
from recon_core.euclidean.control import count_words
from recon_core.io.gcps import picked_positions

from .gcp_session import (
    GcpError,
    add_observation,
    edit_gcp,
    merge_last,
    new_gcp,
    set_affine_position,
    undo,
)
from .picking import pixel_from_ray
from .results import (
    UpgradeOutcome,
    gcp_readiness,
    gcp_state_table,
    gcps_key,
    outcome_markdown,
    run_upgrade,
    upgrade_readiness,
)

if TYPE_CHECKING:
    from .app import ViewerApp


class GcpController:
    """The clicks, the working set's edits and the upgrade of one viewer (`app`)."""

    def __init__(self, app: "ViewerApp"):
        self.app = app
        self.upgrade: UpgradeOutcome | None = None       # the last upgrade the page ran
        self.dsm_rerun_pending = False                   # its DSM still to be recomputed
        self.last_click: tuple | None = None             # (gcp id, image, col, row) of the last pick
        self.armed = None                                # the click callback of a cloud pick
        self.tri_cache: dict = {}                        # (group, gcp, observations) -> affine point
        self._ready_key = None                           # what the readiness below was computed for
        self._readiness: tuple[bool, int, int] = (False, 0, 0)

    # -- GCPs -----------------------------------------------------------------------------------
    def on_plane_click(self, ray_origin, ray_direction, client=None) -> tuple[float, float] | None:
        """A click on the picking plane: an observation of the selected (or a new) GCP; with
        "Click zooms in first", a click outside the loupe opens the loupe there instead."""
        pick = self.app.picking
        if self.armed is not None or pick.plane is None:
            return None
        pix = pixel_from_ray(pick.plane, ray_origin, ray_direction)
        if pix is None:
            self.app.note("the click missed the image", "warning")
            return None
        if self.app.reference is not None and pick.plane.window.image == self.app.reference.ortho.name:
            return self.on_reference_click(pix, client)
        gid = self.app.gcp_panel.selected()
        if gid is None:
            x, y, h, epsg = self.app.gcp_panel.ground()
            if x == 0.0 and y == 0.0:
                raise GcpError("select a GCP, or type the new GCP's ground coordinates "
                               "(or take one from the site list) before clicking")
        self.app.gcp_panel.check_choice(client)
        in_loupe = self._loupe_gate(pix, gid, client)
        if in_loupe is None:
            return None
        if gid is None:
            gid = new_gcp(self.app.session, self.app.gcp_panel.gid.value or None, x=x, y=y, h=h,
                          epsg=epsg, role=self.app.gcp_panel.role.value).id
            created = True
        else:
            created = False
        image = pick.plane.window.image
        try:
            add_observation(self.app.session, gid, image, *pix)
        except GcpError:
            if created:                       # the click created nothing after all
                undo(self.app.session)
            raise
        if created:
            merge_last(self.app.session, 2, f"new {gid} observed in {image}")
            self.app.gcp_panel.note_choice(client, gid)
        self.last_click = (gid, image, pix[0], pix[1])
        if in_loupe:
            pick.close_loupe(client)
        self.changed(select=gid, note=f"{gid}: observed in {image} at col {pix[0]:.2f}, "
                                           f"row {pix[1]:.2f}")
        if in_loupe:                          # a precise click: on to the GCP's next image
            self.app.gcp_panel.walk_on(gid, client)
        return pix

    def on_reference_click(self, pix: tuple[float, float], client=None) -> tuple[float, float] | None:
        """A click on the reference orthoimage: the selected GCP's ground position (lon, lat from
        the orthoimage, h from the DEM), or a new GCP there when none is selected; with "Click
        zooms in first", a click outside the loupe opens the loupe there instead."""
        ref, pick = self.app.reference, self.app.picking
        assert ref is not None               # only a viewer with a reference orthoimage shows it
        self.app.gcp_panel.check_choice(client)
        gid = self.app.gcp_panel.selected()
        in_loupe = self._loupe_gate(pix, gid, client)
        if in_loupe is None:
            return None
        lon, lat, h = ref.ground_at(*pix)
        sigma_h = None
        if h is None:
            h = float(self.app.gcp_panel.h.value) if gid is None else self.app.session.get(gid).h
            where = ("no DEM given (--reference-dem): h kept at " if ref.dem is None
                     else "the DEM has no height there: h kept at ") + f"{h:.2f} m, type it"
        else:
            where, sigma_h = height_words(h, ref.height_doubt(lon, lat), self.views_known())
        if gid is None:
            g = new_gcp(self.app.session, self.app.gcp_panel.gid.value or None, x=lon, y=lat, h=h,
                        role=self.app.gcp_panel.role.value, sigma_h_m=sigma_h)
            self.app.gcp_panel.note_choice(client, g.id)
            what = f"new {g.id}"
        else:
            g = edit_gcp(self.app.session, gid, x=lon, y=lat, h=h,
                         sigma_h_m=sigma_h if ref.dem is not None else "typed")
            what = g.id
        if in_loupe:
            pick.close_loupe(client)
        back = self.app.gcp_panel.walk.value and not g.observations
        self.changed(select=g.id, note=f"{what}: ground position from the reference orthoimage at col "
                                            f"{pix[0]:.2f}, row {pix[1]:.2f}: lon {lon:.7f}, lat {lat:.7f}; "
                                            f"{where}. Now place it in the images"
                                            + (f" ({self.app.gcp_panel.last_site_image} shown)" if back else ""))
        if back:           # "Then its next image": back to the site image shown before the reference
            self.app.gcp_panel.image.value = self.app.gcp_panel.last_site_image
        return pix

    def _loupe_gate(self, pix: tuple[float, float], gid: str | None, client) -> bool | None:
        """Where a click on the plane stands with the loupe: True, in the loupe this GCP and tab
        own (a precise click); False, on the whole image (recorded as it is); None, the click
        opened the loupe there ("Click zooms in first") and records nothing. A click in a loupe
        another GCP or tab owns raises GcpError, saying whose it is."""
        pick = self.app.picking
        assert pick.plane is not None        # the click was on it
        in_loupe = pick.in_loupe(pick.plane.window)
        if in_loupe and not pick.owns_loupe(gid, client):
            raise GcpError(self.not_your_loupe(gid, client))
        if not in_loupe and self.app.gcp_panel.zoom_click.value:
            pick.open_loupe(pix, client, gcp=gid)
            return None
        return in_loupe

    def views_known(self) -> bool:
        """Do two or more images state their viewing direction (the upgrade then takes a GCP's
        doubtful height from them)?"""
        return sum(1 for im in self.app.site.images if im.view is not None) >= 2

    def not_your_loupe(self, gid: str | None, client) -> str:
        """Why a click in the open loupe was not recorded (it is another GCP's, or another tab's)."""
        pick = self.app.picking
        if pick.loupe_gcp != gid:
            return (f"nothing recorded: the loupe shows {pick.loupe_gcp or 'the new GCP'}'s spot, not "
                    f"{gid or 'the new GCP'}'s; Escape leaves it, then click {gid or 'the new GCP'} in the image")
        return ("nothing recorded: the picture is another tab's loupe (40 px around its click, stretched over "
                "the plane); wait for that tab to place it, or press Escape to leave it")

    def arm_cloud_pick(self) -> None:
        """The next click in the scene sets the selected GCP's affine position."""
        gid = self.app.gcp_panel.selected()
        if gid is None:
            raise GcpError("select a GCP first")
        if self.armed is not None:
            self.app.server.scene.remove_click_callback(self.armed)

        def on_click(ev) -> None:
            self.app.submit(lambda: self.on_cloud_click(gid, ev.ray_origin, ev.ray_direction))

        self.armed = on_click
        self.app.server.scene.on_click()(on_click)
        self.app.note(f"click a point of the cloud to place {gid}")

    def on_cloud_click(self, gcp_id: str, ray_origin, ray_direction) -> np.ndarray | None:
        """Set a GCP's affine position to the displayed point nearest to the click ray."""
        if self.armed is not None:
            self.app.server.scene.remove_click_callback(self.armed)
            self.armed = None
        best = self.pick_cloud_point(ray_origin, ray_direction)
        if best is None:
            self.app.note("no point of the cloud near the click; press the button and try again",
                      "warning")
            return None
        g, xyz = best
        set_affine_position(self.app.session, gcp_id, g, xyz)
        self.changed(select=gcp_id, note=f"{gcp_id}: affine position picked on the cloud "
                                              f"of group {g}")
        return xyz

    def pick_cloud_point(self, ray_origin, ray_direction) -> tuple[int, np.ndarray] | None:
        """(group, affine xyz) of the displayed point nearest to a ray, or None."""
        return self.app.scene.nearest_point(ray_origin, ray_direction)

    def changed(self, select: str | None = "keep", note: str | None = None) -> None:
        self.app.gcp_panel.refresh(select)
        self.app.marks.invalidate()
        if note:
            self.app.note(note)
        self.update_upgrade_button()
        self.app.marks.draw()

    def affine_positions(self, g: int) -> dict[str, np.ndarray]:
        """Affine position of every GCP placeable in group g (picked, else triangulated)."""
        from recon_core.euclidean.georef import triangulate_gcp

        model = self.app.models.get(g)
        out = picked_positions(self.app.session.gcps, g)
        if model is None:
            return out
        for gcp in self.app.session.gcps:
            if gcp.id in out:
                continue
            key = (g, gcp.id, tuple(sorted(gcp.observations.items())))
            if key not in self.tri_cache:
                self.tri_cache[key] = triangulate_gcp(model, gcp.observations).xyz
            if self.tri_cache[key] is not None:
                out[gcp.id] = self.tri_cache[key]
        return out

    # -- upgrade --------------------------------------------------------------------------------
    def upgrade_maps(self) -> UpgradeMaps | None:
        """Each upgraded group's map to local ENU and the frame, of the upgrade the viewer
        shows: the last one the page ran, else the one OUT holds (a finished or reopened run);
        None before any. What predicts a GCP from its surveyed position."""
        if self.upgrade is not None:
            fits = self.upgrade.fits(self.app.models)      # a group's model replaced since: not its map
            maps = {g: m for g, m in self.upgrade.maps.items() if g in fits}
            return UpgradeMaps(maps, self.upgrade.frame) if maps else None
        return self.app.saved_upgrade

    def update_upgrade_button(self) -> None:
        """The Results tab's Upgrade button and its lists. The readiness (which triangulates every
        control GCP in every group) and the state table are recomputed only when the GCPs, the
        models, the configuration or the upgrade (its predictions from the surveyed positions)
        change, not at every update of the panel."""
        app = self.app
        key = (app.session.version, tuple(id(m) for m in app.models.values()), id(app.cfg), id(self.upgrade),
               id(app.saved_upgrade))
        if key != self._ready_key:
            self._ready_key = key
            ready = gcp_readiness(app.session, app.models)
            self._readiness = upgrade_readiness(app.session, app.models, {im.name: im for im in app.site.images},
                                                app.cfg)

            def doubt(gid: str) -> str:
                sh = app.session.get(gid).sigma_h_m
                return "" if sh is None else f"; **height known only to +- {sh:.1f} m** (from the DEM)"
            app.set_md(app.g_ready_list, "\n".join(f"- {gid} ({app.session.get(gid).role}): {txt}{doubt(gid)}"
                                                    for gid, (_, txt) in ready.items()))
            app.set_md(app.g_state_table, gcp_state_table(app.session, app.models, sorted(app.session.images),
                                                          self.upgrade_maps()))
        can, n, need = self._readiness
        app.g_upgrade.disabled = not (bool(app.models) and can)
        why = "waiting for the sparse model" if not app.models else count_words(n, need)
        stale = ""
        if self.upgrade is not None and self.upgrade.gcps_key != gcps_key(app.session):
            stale = "\n\n*The GCPs changed since the last upgrade: press Upgrade again.*"
        elif self.upgrade is not None and not set(self.upgrade.maps) <= self.upgrade.fits(app.models):
            stale = ("\n\n*The reconstruction changed since the last upgrade (a new bundle adjustment): "
                     "press Upgrade again.*")
        app.set_md(app.g_ready, f"{why}.{stale}")

    def do_upgrade(self) -> UpgradeOutcome:
        """The Upgrade button: fit H_A with the pipeline's own function, switch the scene to
        the Euclidean frame, show the residuals, then recompute the DSM and the error map from
        this GCP set (the pipeline from its upgrade stage, as `aerec run --redo-from upgrade`)."""
        try:
            outcome = run_upgrade(self.app.session, self.app.models, self.app.cfg, {im.name: im for im in self.app.site.images})
        except AerecError as exc:
            text = str(exc).replace("set upgrade.allow_flat_gcps = true (aerec run --config FILE)",
                                    "tick *Accept GCPs nearly on one plane* above and press Upgrade again; or "
                                    "add a control GCP off their plane")
            self.app.set_md(self.app.g_upgrade_md, f"**Upgrade failed:** {text}")
            raise
        self.upgrade = outcome
        self.app.gcp_panel.listing.content = self.app.gcp_panel.working_set_table()   # each GCP's error now
        self.app._euclid = {g: outcome.transform(g) for g in outcome.results}
        self.app.set_md(self.app.g_upgrade_md, outcome_markdown(outcome))
        self.app.g_frame_sel.disabled = False
        self.app.set_frame("euclidean")
        self.update_upgrade_button()
        self.dsm_rerun_pending = True
        self.start_dsm_rerun()
        return outcome

    def allow_flat(self, on: bool) -> None:
        """The Results tab's "Accept GCPs nearly on one plane": upgrade.allow_flat_gcps for this
        session's upgrades and the DSM they recompute."""
        self.app.cfg = self.app.cfg.with_overrides({"upgrade.allow_flat_gcps": on})
        self.app.worker.cfg = self.app.cfg
        self.app.note("GCPs nearly on one plane are " + ("accepted: the result says the height error to expect; "
                                                         "press Upgrade" if on else "refused again"))

    def start_dsm_rerun(self) -> None:
        """Start the pending re-run from the upgrade stage once the worker is free; say why
        when it cannot be done at all."""
        if not self.dsm_rerun_pending or self.app._stop.is_set():
            return
        why = self.app.worker.rerun_from("upgrade")
        if why == "busy":
            return                                  # tried again when the current run is done
        self.dsm_rerun_pending = False
        if why is None:
            self.app.note("recomputing the upgrade records, the DSM and the error map from the "
                      "working GCP set (as `aerec run --redo-from upgrade`)")
        else:
            self.app.note(f"the DSM is not recomputed from this upgrade: {why}", "warning")


def height_words(h: float, doubt, views_known: bool) -> tuple[str, float | None]:
    """(what the operator reads about a height taken from the DEM, its sigma when doubtful)."""
    where = f"h {h:.2f} m from the DEM"
    if doubt is None or doubt.flat:
        return where, None
    what = ("the upgrade takes its height from the images' viewing angles (\"Take the images' height\" "
            "after it), or type the surveyed height" if views_known else
            "type its surveyed height, or pick a spot on flat ground (the images do not state their "
            "viewing angles, so the upgrade cannot tell its height)")
    return (where + f", **known only to +- {doubt.sigma_m:.1f} m**: the DEM changes by {doubt.spread_m:.1f} m "
            f"within {doubt.radius_m:.0f} m of the spot (its cells are {doubt.cell_m:.0f} m: a roof or a "
            f"wall gets a height between the top's and the ground's); {what}"), doubt.sigma_m
