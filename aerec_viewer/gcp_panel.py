"""The GCP tab: its widgets and what they do. The edits themselves are gcp_session's; the
picking plane and its loupe, where a click becomes a pixel, are the picking view's (picking)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Protocol

import numpy as np

from recon_core.euclidean.gcp_transfer import place_in_other_images

from .gcp_session import (
    ROLES,
    GcpError,
    GcpSession,
    add_observation,
    can_redo,
    can_undo,
    default_epsg,
    delete_gcp,
    describe,
    edit_gcp,
    ground_to_llh,
    nudge_observation,
    import_site_gcps,
    merge_gcps,
    merge_last,
    new_gcp,
    redo,
    remove_observation,
    set_affine_position,
    set_enabled,
    toggle_role,
    undo,
)
from .picking import PickingView

if TYPE_CHECKING:
    from .gcp_controller import GcpController


def upgrade_errors(outcome) -> dict[str, str]:
    """GCP id -> "dE / dN / dU" (m) from an upgrade's rows (the first group that scores it): a
    control point's leave-one-out error (marked *) where there is one, else its residual."""
    out: dict[str, str] = {}
    if outcome is None:
        return out
    for g in sorted(outcome.results):
        for p in outcome.results[g].points:
            if p["id"] in out or p.get("dU") is None:
                continue
            loo = p.get("loo_dU") is not None and p["role"] == "control"
            e, n, u = (p[f"loo_d{a}"] if loo else p[f"d{a}"] for a in "ENU")
            out[p["id"]] = f"{e:+.2f} / {n:+.2f} / {u:+.2f}" + ("*" if loo else "")
    return out


class GcpPanelHost(Protocol):
    """What the GCP tab needs of the viewer: the working set, the site, a way to run work on the
    update thread, and the scene actions its buttons trigger."""

    session: GcpSession
    site: object
    models: dict                      # group -> SparseModel once the sparse stage is done

    picking: PickingView               # the picking plane and its loupe
    gcp: GcpController                 # the clicks, the working set's edits, the upgrade

    def submit(self, fn: Callable[[], object]) -> object: ...
    def note(self, text: str, level: str = "info") -> None: ...


# -- the panel --------------------------------------------------------------------------------
class GcpPanel:
    """Widgets of the GCP tab. Callbacks queue work on the app's update thread."""

    NEW = "(new GCP from the fields below)"
    CONFIRM_S = 10.0          # a second press of Delete within this time confirms

    def __init__(self, app: GcpPanelHost, gui):
        self.app = app
        s = app.session
        names = sorted(s.images)
        self.last_site_image = names[0]
        ref = getattr(app, "reference", None)
        self.image = gui.add_dropdown("Image", names + ([ref.ortho.name] if ref is not None else []),
                                      initial_value=names[0],
                                      hint=None if ref is None else "the reference orthoimage (last): "
                                      "a click there gives the selected GCP its ground position, or "
                                      "makes a new GCP there")
        self.region = gui.add_dropdown("Region", ["whole image"], initial_value="whole image",
                                       hint="pick a tile to see it at full resolution")
        self.show_plane = gui.add_checkbox("Show image plane", True)
        self.contrast = gui.add_dropdown("Contrast", ["window", "image", "site"], initial_value="window",
                                         hint="window: stretched on what is shown (the loupe's "
                                              "pixels: a roof corner in shadow keeps its detail); "
                                              "image: this image's own; site: one stretch for all "
                                              "images (they look alike)")
        self.goto = gui.add_button("Look at the image plane", icon=None)
        self.zoom_click = gui.add_checkbox(
            "Click zooms in first (loupe)", True,
            hint="the first click on the image shows its full-resolution pixels around that point, "
                 "enlarged, with a crosshair; the click there places the GCP and goes back")
        self.walk = gui.add_checkbox(
            "Then its next image", True,
            hint="after a click in the loupe (or Enter on a prediction), the GCP's next image "
                 "without an observation opens in the loupe at its predicted pixel")
        self.leave_loupe = gui.add_button("Leave the loupe", disabled=True)
        gui.add_markdown("Click a pixel on the image plane: it becomes an observation of the GCP "
                         "selected here (or of a new GCP with the fields below). Shift+click "
                         "zooms toward the spot under the cursor, Ctrl+Shift+click back out.")
        self.select = gui.add_dropdown("GCP", [self.NEW], initial_value=self.NEW)
        self.prev_gcp = gui.add_button("Previous GCP")
        self.next_gcp = gui.add_button("Next GCP")
        self.info = gui.add_markdown("")
        self.jump = gui.add_dropdown("Go to its observation", [self.JUMP_NONE], initial_value=self.JUMP_NONE,
                                     hint="opens the loupe on the selected GCP's observation in that "
                                          "image: a click there moves it")
        self.role_toggle = gui.add_button("Make it a check point", disabled=True,
                                          hint="control points enter the fit; check points are only scored")
        self.enable_toggle = gui.add_button("Disable it", disabled=True,
                                            hint="a disabled GCP keeps its observations but is left "
                                                 "out of the upgrade (fit and scores)")
        self.nudge_step = gui.add_dropdown("Nudge step", self.NUDGE_STEPS, initial_value=self.NUDGE_STEPS[0],
                                           hint="how far a nudge moves the selected GCP's observation")
        self.nudges = gui.add_button_group("Nudge it", list(self.NUDGE_DIRS),
                                           hint="moves the selected GCP's observation in the image shown "
                                                "(image pixels; up: towards row 0)")
        self.take_height = gui.add_button(
            "Take the images' height", disabled=True,
            hint="for a GCP whose height is doubtful (read off the DEM at a roof or a wall): the "
                 "height the last upgrade's images put it at")
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
        with gui.add_folder("Working set", expand_by_default=True):
            self.listing = gui.add_markdown("")
        with gui.add_folder("Markers as CSV", expand_by_default=False):
            gui.add_markdown("One row per observation: `id, role, x, y, h, epsg, sigma_m, image, col, row` "
                             "(x, y: lon, lat for epsg 4979, else E, N), as `aerec gcps convert` reads.")
            self.export_csv = gui.add_button("Export the working set (CSV)")
            self.import_csv = gui.add_upload_button("Import markers (CSV)", mime_type=".csv,text/csv,text/plain",
                                                    hint="adds new GCPs; a known id takes the file's ground "
                                                         "position, role and observations (one Undo)")
        with gui.add_folder("Site GCP list", expand_by_default=False):
            cat = [g.id for g in s.catalogue] or ["(the site has no gcps.geojson)"]
            self.catalogue = gui.add_dropdown("Site GCP", cat, initial_value=cat[0])
            self.take = gui.add_button("Add it (ground coordinates only)")
            self.take_all = gui.add_button("Add all site GCPs with their observations")
        self.predict = gui.add_button("Predict its position in this image",
                                      hint="from its observations in the other images (and the "
                                           "sparse surface), refined by image matching")
        self.accept = gui.add_button("Accept the prediction", disabled=True)
        self.place_all = gui.add_button(
            "Place it in its other images", hint="predict it in every image of its group where it "
            "has no observation yet and record the predictions that image matching confirms")
        self.pick_cloud = gui.add_button("Pick its position on the cloud (next click)")
        self.forget_pick = gui.add_button("Forget its cloud pick",
                                          hint="the image observations are used again")
        self.unobserve = gui.add_button("Remove its observation in this image")
        self.delete = gui.add_button("Delete the selected GCP", color="red")
        self.undo = gui.add_button("Undo", disabled=True)
        self.redo = gui.add_button("Redo", disabled=True)
        self.status = gui.add_markdown("")
        self._delete_armed: tuple[str, float] | None = None
        self.prediction = None              # (gid, Prediction) shown, waiting for Accept
        self.chosen: dict[int, str] = {}     # client id -> what that tab chose or saw in the GCP list
        self._ids: dict[str, str] = {}       # entry of the GCP list -> GCP id (refresh)
        self.last_chooser: tuple[int, str] | None = None   # the tab that changed the list last, and to what
        self._wire()
        self.shortcuts = self._add_shortcuts(gui)
        gui.add_markdown("Keys: " + ", ".join(f"**{k}** {what}" for k, what, _ in self.shortcut_rows())
                         + " (viser's W A S D Q E and arrows move the camera).")

    # key, what, action (the camera keeps viser's W A S D Q E and arrow keys)
    SHORTCUTS = (
        ("N", "next GCP", lambda self, ev: self.step_gcp(+1, ev.client)),
        ("P", "previous GCP", lambda self, ev: self.step_gcp(-1, ev.client)),
        ("I", "next image", lambda self, ev: self.step_image(+1)),
        ("shift+I", "previous image", lambda self, ev: self.step_image(-1)),
        ("L", "look at the image plane", lambda self, ev: self.app.picking.look_at_plane(ev.client)),
        ("R", "predict in this image", lambda self, ev: self._predict()),
        ("enter", "accept the prediction", lambda self, ev: self._accept(ev.client)),
        ("O", "place it in its other images", lambda self, ev: self._place_all(ev.client)),
        ("escape", "leave the loupe", lambda self, ev: self.app.picking.close_loupe(ev.client)),
        ("ctrl+Z", "undo", lambda self, ev: self._undo()),
        ("ctrl+shift+Z", "redo", lambda self, ev: self._redo()),
    )
    # the nudge buttons: the selected GCP's observation in the image shown moves by the step
    # chosen (viser's arrow keys turn the camera, so the nudges are buttons)
    NUDGE_STEPS = ("0.1 px", "0.5 px", "1 px")
    NUDGE_DIRS = {"left": (-1, 0), "right": (1, 0), "up": (0, -1), "down": (0, 1)}
    # with a reference orthoimage (aerec view --reference-ortho)
    REFERENCE_SHORTCUTS = (
        ("G", "a new GCP on the reference orthoimage", lambda self, ev: self.new_on_reference()),
    )

    def shortcut_rows(self) -> tuple:
        """SHORTCUTS, and REFERENCE_SHORTCUTS when the viewer has a reference orthoimage."""
        return self.SHORTCUTS + (self.REFERENCE_SHORTCUTS if getattr(self.app, "reference", None) else ())

    def nudge(self, dcol: float, drow: float) -> tuple[float, float]:
        """Move the selected GCP's observation in the image shown by (dcol, drow) pixels."""
        gid = self.selected()
        if gid is None:
            raise GcpError("select a GCP first")
        plane = self.app.picking.plane
        image = plane.window.image if plane is not None else self.image.value
        if image not in self.app.session.images:
            raise GcpError("nudges move an observation in a site image; on the reference orthoimage, "
                           "click the spot again")
        c, r = nudge_observation(self.app.session, gid, image, dcol, drow)
        self.app.gcp.changed(select=gid, note=f"{gid} in {image}: col {c:.2f}, row {r:.2f}")
        return c, r

    def new_on_reference(self) -> None:
        """Select "(new GCP ...)" and show the reference orthoimage: the next click there (through
        the loupe) makes a GCP at that ground position."""
        ref = getattr(self.app, "reference", None)
        if ref is None:
            raise GcpError("no reference orthoimage (aerec view --reference-ortho FILE)")
        self.refresh(select=None)
        if self.image.value != ref.ortho.name:
            self.image.value = ref.ortho.name
        self.app.note("a new GCP: click its spot on the reference orthoimage (its ground position "
                      "comes from there), then place it in the images")

    def _add_shortcuts(self, gui) -> dict[str, object]:
        """One viser command (palette entry + hotkey) per SHORTCUTS row; its action runs on the
        update thread like a button's. Empty when this viser has no commands."""
        if not hasattr(gui, "add_command"):
            return {}
        out = {}
        for key, what, action in self.shortcut_rows():
            mods, _, hot = key.rpartition("+")
            modifier = {"": None, "ctrl": "cmd/ctrl", "shift": "shift", "alt": "alt",
                        "alt+shift": "alt+shift", "ctrl+shift": "cmd/ctrl+shift"}[mods]
            h = gui.add_command(what.capitalize(), hotkey=hot if len(hot) > 1 else hot.upper(),
                                modifier=modifier)
            h.on_trigger(lambda ev, action=action: self.app.submit(lambda: action(self, ev)))
            out[key] = h
        return out

    def step_image(self, step: int) -> str:
        """Show the next (+1) or previous (-1) image on the picking plane, wrapping."""
        names = list(self.image.options)
        new = names[(names.index(self.image.value) + step) % len(names)]
        self.image.value = new     # its on_update drops the prediction and the loupe, redraws
        return new

    def _wire(self) -> None:
        app = self.app
        def image_chosen(ev) -> None:
            v = ev.target.value
            if v in self.app.session.images:
                self.last_site_image = v           # where a click on the reference sends back to
            app.submit(lambda: (self.drop_prediction(), self.app.picking.close_loupe(), self.app.picking.show()))
        self.image.on_update(image_chosen)
        self.region.on_update(lambda _: app.submit(lambda: (self.app.picking.close_loupe(),
                                                            self.app.picking.show())))
        self.leave_loupe.on_click(lambda ev: app.submit(lambda: self.app.picking.close_loupe(ev.client)))
        self.prev_gcp.on_click(lambda ev: app.submit(lambda: self.step_gcp(-1, ev.client)))
        self.next_gcp.on_click(lambda ev: app.submit(lambda: self.step_gcp(+1, ev.client)))
        self.place_all.on_click(lambda ev: app.submit(lambda: self._place_all(ev.client)))
        self.show_plane.on_update(lambda _: app.submit(self.app.picking.show))
        self.contrast.on_update(lambda _: app.submit(self.app.picking.show))
        self.goto.on_click(lambda ev: app.submit(lambda: self.app.picking.look_at_plane(ev.client)))
        def chosen(ev) -> None:          # the GCP this tab chose, read now, not when queued
            v = self.id_of(ev.target.value) or self.NEW
            # the operator's own choice in the list is described; a selection made by the code
            # (N, a new GCP, an edit) comes with its own note, which this must not overwrite
            app.submit(lambda: (self.note_choice(ev.client, v), self.drop_prediction(),
                                self.app.picking.retarget(None if v == self.NEW else v), self.fill_fields(),
                                ev.client is not None and v != self.NEW and v in self.app.session.ids
                                and self.app.note(self.selection_note(v))))
        self.select.on_update(chosen)
        self.crs.on_update(lambda _: app.submit(self._convert_fields))
        self.apply.on_click(lambda _: app.submit(self._apply))
        self.create.on_click(lambda _: app.submit(self._create))
        self.take.on_click(lambda _: app.submit(self._take))
        self.take_all.on_click(lambda _: app.submit(self._take_all))
        self.pick_cloud.on_click(lambda _: app.submit(self.app.gcp.arm_cloud_pick))
        self.unobserve.on_click(lambda _: app.submit(self._unobserve))
        self.delete.on_click(lambda _: app.submit(self._delete))
        self.forget_pick.on_click(lambda _: app.submit(self._forget_pick))
        self.jump.on_update(lambda ev: app.submit(lambda: self._on_jump(ev.client)))
        self.role_toggle.on_click(lambda _: app.submit(self._toggle_role))
        self.enable_toggle.on_click(lambda _: app.submit(self._toggle_enabled))
        self.take_height.on_click(lambda _: app.submit(self.take_images_height))
        self.export_csv.on_click(lambda ev: app.submit(lambda: self.export_markers(ev.client)))
        self.import_csv.on_upload(lambda ev: app.submit(
            lambda f=ev.target.value: self.import_markers(f.name, f.content)))
        def nudged(ev) -> None:
            (dc, dr), step = self.NUDGE_DIRS[ev.target.value], float(self.nudge_step.value.split()[0])
            app.submit(lambda: self.nudge(dc * step, dr * step))
        self.nudges.on_click(nudged)
        self.predict.on_click(lambda _: app.submit(self._predict))
        self.accept.on_click(lambda ev: app.submit(lambda: self._accept(ev.client)))
        self.undo.on_click(lambda _: app.submit(self._undo))
        self.redo.on_click(lambda _: app.submit(self._redo))

    # -- actions (update thread) ----------------------------------------------------------------
    def selected(self) -> str | None:
        """The GCP chosen in the list (its id), None for a new one."""
        return self.id_of(self.select.value)

    def id_of(self, option: str) -> str | None:
        """The GCP id behind an entry of the list (None: the new-GCP entry)."""
        return None if option == self.NEW else self._ids.get(option, option)

    def option_of(self, gid: str | None) -> str:
        """The list's entry for a GCP: its id, role and the registered images it is placed in
        (what an operator scans the list for), or the new-GCP entry."""
        if gid is None or gid not in self.app.session.ids:
            return self.NEW
        g = self.app.session.get(gid)
        images = self._registered_images()
        role = g.role if g.enabled else "off"
        return f"{gid} · {role} · {len(set(g.observations) & images)}/{len(images)}"

    def select_id(self, gid: str | None) -> None:
        """Show a GCP (by id) as chosen in the list."""
        self.select.value = self.option_of(gid)

    def ground(self) -> tuple[float, float, float, int | None]:
        epsg = int(self.epsg.value) if self.crs.value.startswith("E") else None
        return float(self.x.value), float(self.y.value), float(self.h.value), epsg

    def _convert_fields(self) -> None:
        """Switching between lon/lat and E/N converts the typed coordinates."""
        from recon_core.geometry.geodesy import geodetic_to_projected

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
        x, y, h, epsg = self.ground()
        g = edit_gcp(self.app.session, gid, new_id=self.gid.value, x=x, y=y, h=h, epsg=epsg,
                     role=self.role.value)
        self.app.gcp.changed(select=g.id, note=f"{g.id} updated")

    def _create(self) -> None:
        x, y, h, epsg = self.ground()
        g = new_gcp(self.app.session, self.gid.value or None, x=x, y=y, h=h, epsg=epsg,
                    role=self.role.value)
        self.app.gcp.changed(select=g.id, note=f"{g.id} created: now click its pixel")

    def _take(self) -> None:
        added = import_site_gcps(self.app.session, [self.catalogue.value], with_observations=False)
        self.app.gcp.changed(select=added[0] if added else self.catalogue.value,
                              note=f"added {added[0]}: click its pixel in each image" if added
                              else f"{self.catalogue.value} is already in the GCP list")

    def _take_all(self) -> None:
        added = import_site_gcps(self.app.session, None, with_observations=True)
        self.app.gcp.changed(note=f"added {len(added)} site GCP(s)")

    def _unobserve(self) -> None:
        gid = self.selected()
        if gid is None:
            raise GcpError("select a GCP first")
        remove_observation(self.app.session, gid, self.image.value)
        self.app.gcp.changed(select=gid, note=f"removed {gid}'s observation in {self.image.value}")

    def _delete(self) -> None:
        """First press: ask for confirmation (the button says what will go); a second press on
        the same GCP within CONFIRM_S seconds deletes it (Undo brings it back)."""
        gid = self.selected()
        if gid is None:
            raise GcpError("select a GCP first")
        armed = self._delete_armed
        if armed is None or armed[0] != gid or time.monotonic() - armed[1] > self.CONFIRM_S:
            n = len(self.app.session.get(gid).observations)
            self._delete_armed = (gid, time.monotonic())
            self.delete.label = f"Confirm: delete {gid} and its {n} observation(s)"
            self.app.note(f"press the button again to delete {gid} ({n} observation(s))", "warning")
            return
        self._disarm_delete()
        delete_gcp(self.app.session, gid)
        self.app.gcp.changed(select=None, note=f"deleted {gid} (Undo restores it)")

    def _disarm_delete(self) -> None:
        self._delete_armed = None
        self.delete.label = "Delete the selected GCP"

    JUMP_NONE = "(choose an image)"

    def jump_to(self, image: str, client=None) -> None:
        """Show the selected GCP's observation in `image` in the loupe (a click there moves it)."""
        gid = self.selected()
        if gid is None:
            raise GcpError("select a GCP first")
        obs = self.app.session.get(gid).observations
        if image not in obs:
            raise GcpError(f"{gid} has no observation in {image}")
        col, row = obs[image]
        self._loupe_after_switch(gid, image, (col, row), client,
                                 f"{gid} in {image} at col {col:.2f}, row {row:.2f}: a click in the "
                                 "loupe moves it, Escape leaves it as it is")

    def _loupe_after_switch(self, gid: str, image: str, pix: tuple[float, float], client,
                            note: str, before_open: Callable[[], None] | None = None) -> None:
        """Switch the plane to `image` (its callback queues the redraw and drops any prediction),
        then, queued behind it, open the loupe at `pix`, unless the operator acted in between
        (Undo, N, another image, an edit of this GCP): what is shown must match the state it
        was computed from."""
        if self.image.value != image:
            self.image.value = image
        made_from = dict(self.app.session.get(gid).observations)

        def show() -> None:
            if (gid not in self.app.session.ids or self.selected() != gid or self.image.value != image
                    or dict(self.app.session.get(gid).observations) != made_from):
                return
            if before_open is not None:
                before_open()
            self.app.picking.open_loupe(pix, client, image=image, gcp=gid)
            self.app.note(note)
        self.app.submit(show)

    def _on_jump(self, client=None) -> None:
        image = self.jump.value
        if image == self.JUMP_NONE:
            return
        self.jump.value = self.JUMP_NONE
        self.jump_to(image, client)

    def residuals(self, gid: str) -> dict[str, float]:
        """Image -> reprojection residual (px) of the GCP's observations, per group."""
        from recon_core.euclidean.gcp_transfer import observation_residuals

        g = self.app.session.get(gid)
        out: dict[str, float] = {}
        for m in self.app.models.values():
            out.update({im: float(np.hypot(*v)) for im, v in observation_residuals(m, g.observations).items()})
        return out

    def _toggle_role(self) -> None:
        gid = self.selected()
        if gid is None:
            raise GcpError("select a GCP first")
        g = toggle_role(self.app.session, gid)
        self.app.gcp.changed(select=gid, note=f"{gid} is now a {g.role} point")

    def _toggle_enabled(self) -> None:
        gid = self.selected()
        if gid is None:
            raise GcpError("select a GCP first")
        g = set_enabled(self.app.session, gid, not self.app.session.get(gid).enabled)
        self.app.gcp.changed(select=gid, note=f"{gid} {'enabled' if g.enabled else 'disabled: the upgrade leaves it out'}")

    def export_markers(self, client=None) -> str:
        """The working set as CSV, sent to the tab that asked (and returned)."""
        from recon_core.io.gcps_csv import gcps_csv_text

        text = gcps_csv_text(self.app.session.gcps)
        if client is not None:
            client.send_file_download(f"{self.app.site.name}_gcps.csv", text.encode())
        self.app.note(f"{len(self.app.session.gcps)} GCP(s) exported as CSV")
        return text

    def import_markers(self, name: str, content: bytes) -> tuple[list[str], list[str]]:
        """Read a marker CSV (as `aerec gcps convert` does) into the working set."""
        import tempfile

        from recon_core.errors import InputError
        from recon_core.io.gcps_csv import read_gcps_csv

        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / (Path(name).name or "markers.csv")
            path.write_bytes(content)
            try:
                gcps = read_gcps_csv(path)
            except InputError as exc:
                raise GcpError(f"{name}: {exc.problem}") from None
        added, updated = merge_gcps(self.app.session, gcps, source=name)
        self.app.gcp.changed(note=f"{name}: {len(added)} GCP(s) added"
                                   + (f" ({', '.join(added)})" if added else "")
                                   + f", {len(updated)} updated" + (f" ({', '.join(updated)})" if updated else ""))
        return added, updated

    # a height the images give better than this is taken as known (the flag cleared)
    HEIGHT_KNOWN_M = 0.3

    def take_images_height(self) -> float:
        """Set the selected GCP's height to the one the last upgrade's images give it; it stays
        flagged, with the images' sigma, when they give it no better than HEIGHT_KNOWN_M."""
        from .results import images_height

        gid = self.selected()
        if gid is None:
            raise GcpError("select a GCP first")
        g = self.app.session.get(gid)
        got = images_height(self.app.gcp.upgrade, g)
        if got is None:
            raise GcpError(f"no upgrade has placed {gid} yet: place it in two images, press Upgrade "
                           "(Results tab), then take its height")
        h, sig = got
        old = g.h
        known = sig is not None and sig <= self.HEIGHT_KNOWN_M
        edit_gcp(self.app.session, gid, x=g.lon, y=g.lat, h=h, sigma_h_m=None if known else
                 (sig if sig is not None else g.sigma_h_m))
        text = f"{gid}: height {h:.2f} m from the images (was {old:.2f} m, {h - old:+.2f} m)"
        if known:
            text += f", known to +- {sig:.2f} m; press Upgrade again"
        else:
            text += (f", known only to +- {sig:.1f} m" if sig is not None else ", how well is not known") + (
                ": still doubtful. The other control GCPs' heights are doubtful too, or the images "
                "hold the heights weakly here: add a control GCP on flat ground (its DEM height is "
                "then trusted) or type the surveyed height, and press Upgrade again")
        self.app.gcp.changed(select=gid, note=text)
        return h

    def _forget_pick(self) -> None:
        gid = self.selected()
        if gid is None:
            raise GcpError("select a GCP first")
        groups = sorted(self.app.session.get(gid).affine_picked)
        if not groups:
            raise GcpError(f"{gid} has no position picked on the cloud")
        for g in groups:
            set_affine_position(self.app.session, gid, g, None)
        merge_last(self.app.session, len(groups), f"forget {gid}'s cloud pick")
        self.app.gcp.changed(select=gid, note=f"{gid}: cloud pick forgotten, its image "
                                               "observations are used again")

    def _predict(self):
        """Predict the selected GCP's pixel in the plane's image; Accept records it."""
        from recon_core.euclidean.gcp_transfer import predict_observation

        gid = self.selected()
        if gid is None:
            raise GcpError("select a GCP first")
        image = self.image.value
        ref = getattr(self.app, "reference", None)
        if ref is not None and image == ref.ortho.name:
            raise GcpError("the reference orthoimage gives ground positions, not observations: click "
                           f"{gid}'s spot on it, or choose one of the site's images to predict in")
        g = self.app.session.get(gid)
        model = next((m for m in self.app.models.values() if image in m.images), None)
        if model is None:
            raise GcpError(f"no registered model holds {image} yet (wait for the sparse stage)")
        images = {im.name: im for im in self.app.site.images}
        pred = predict_observation(model, images, g.observations, image)
        if pred is None:
            raise GcpError(f"cannot predict {gid} in {image}: observe it in another image of its "
                           "group first (where a registered tile contains it)")
        self.prediction = (gid, pred)
        self.accept.disabled = False
        self.accept.label = f"Accept: {gid} at col {pred.col:.2f}, row {pred.row:.2f}"
        self.app.note(f"{gid} predicted in {image} at col {pred.col:.2f}, row {pred.row:.2f} "
                      f"({pred.how}; {pred.uncertainty()}); Accept records it, or click the right pixel")
        return pred

    def note_choice(self, client, value: str | None = None, chooser: bool = True) -> None:
        """Remember what this tab chose in the GCP list (the list itself is shared by all tabs);
        `chooser`: the tab changed the list itself (not only looked at it)."""
        if client is None:
            return
        v = (self.selected() or self.NEW) if value is None else value
        self.chosen[client.client_id] = v
        if chooser:
            self.last_chooser = (client.client_id, v)

    def check_choice(self, client) -> None:
        """Before a click records an observation: the GCP list is shared between tabs, so if
        another tab has chosen the GCP now shown since this tab chose or saw its own, the click
        must not land on the other tab's GCP. It records nothing and says so (the next click goes
        to what is shown). One tab alone is never refused, whatever its actions did to the list."""
        if client is None:
            return
        cur = self.selected() or self.NEW
        mine = self.chosen.get(client.client_id)
        self.chosen[client.client_id] = cur
        other = self.last_chooser
        if mine is not None and mine != cur and other is not None and other[0] != client.client_id \
                and other[1] == cur:
            raise GcpError(f"another tab changed the GCP to {cur} after this tab chose {mine}: the "
                           f"click recorded nothing; click again to place {cur}, or choose another")

    def _registered_images(self) -> set[str]:
        """The images the reconstruction registered (every image of the site before the sparse
        stage has)."""
        if self.app.models:
            return set().union(*(m.images for m in self.app.models.values()))
        return {im.name for im in self.app.site.images}

    def finished(self, gid: str, images: set[str] | None = None) -> bool:
        """Observed in every registered image (`images`, when the caller has them): nothing left
        to place."""
        images = self._registered_images() if images is None else images
        return images <= set(self.app.session.get(gid).observations)

    def selection_note(self, gid: str) -> str:
        g = self.app.session.get(gid)
        n = len(g.observations)
        return (f"{gid} selected ({g.role}{'' if g.enabled else ', disabled'}): observed in {n} "
                f"image(s)" + (", every registered one" if n and self.finished(gid) else ""))

    def neighbour(self, gid: str | None, step: int) -> tuple[str, int]:
        """(the GCP N (+1) or P (-1) selects from `gid`, how many finished ones it passes over)."""
        ids = self.app.session.ids
        images = self._registered_images()
        todo = {g for g in ids if not self.finished(g, images)}
        pool = todo if todo - {gid} else set(ids)
        start = ids.index(gid) if gid in ids else (-1 if step > 0 else 0)
        for k in range(1, len(ids) + 1):
            new = ids[(start + step * k) % len(ids)]
            if new in pool:
                return new, k - 1          # the finished ones stepped over on the way
        raise AssertionError("unreachable: the pool is never empty")

    def step_gcp(self, step: int, client=None) -> str | None:
        """Select the next (step +1) or previous (-1) GCP of the working set, wrapping, passing
        over the finished ones (observed in every registered image) while any is not."""
        ids = self.app.session.ids
        if not ids:
            raise GcpError("the GCP list is empty: add a GCP first")
        new, skipped = self.neighbour(self.selected(), step)
        self.app.picking.retarget(new)             # the last GCP's loupe must not place this one
        self.app.gcp.changed(select=new, note=self.selection_note(new) + (
            f"; {skipped} finished GCP(s) passed over" if skipped else ""))
        self.note_choice(client, new)
        return new

    def _place_all(self, client=None) -> dict[str, str]:
        """Predict the selected GCP in every image of its group(s) where it has no observation and
        record the predictions that are triangulated from >= 2 observations, or confirmed by
        matching *and* consistent with its other observations (one undo step); the others are
        named with why they were left for the operator, and the first of them that has a
        prediction is shown at once: its image on the plane, the loupe open at the predicted
        pixel (a click there places it, Enter accepts the prediction as it is)."""
        gid = self.selected()
        if gid is None:
            raise GcpError("select a GCP first")
        g = self.app.session.get(gid)
        if not g.observations:
            raise GcpError(f"{gid} has no observation yet: click it in one image first")
        images = {im.name: im for im in self.app.site.images}
        done, left, hints = {}, {}, {}
        for model in self.app.models.values():
            seen = {im: xy for im, xy in g.observations.items() if im in model.images}
            if seen:
                placed, why, hint = place_in_other_images(model, images, seen)
                for image, pred in placed.items():
                    add_observation(self.app.session, gid, image, pred.col, pred.row)
                    done[image] = f"col {pred.col:.2f}, row {pred.row:.2f} ({pred.how})"
                left.update(why)
                hints.update(hint)
        if done:
            merge_last(self.app.session, len(done), f"{gid} placed in {len(done)} image(s) by prediction")
        note = (f"{gid}: placed in {', '.join(f'{k} at {v}' for k, v in done.items()) or 'no image'}"
                + (f"; left to you: {'; '.join(f'{k}: {v}' for k, v in left.items())}" if left else ""))
        self.app.gcp.changed(select=gid, note=note)
        if hints:
            self.show_hint(gid, next(iter(hints.values())), client)
        return {**{k: "placed" for k in done}, **left}

    def show_hint(self, gid: str, pred, client=None) -> None:
        """Show an image left to the operator: the plane switches to it (queued redraw), then the
        loupe opens at the prediction, which Enter accepts as it is."""
        def offer() -> None:
            self.prediction = (gid, pred)
            self.accept.disabled = False
            self.accept.label = f"Accept: {gid} at col {pred.col:.2f}, row {pred.row:.2f}"
        self._loupe_after_switch(gid, pred.image, (pred.col, pred.row), client,
                                 f"{gid} in {pred.image}: predicted at col {pred.col:.2f}, row "
                                 f"{pred.row:.2f} ({pred.how}; {pred.uncertainty()}), shown in the "
                                 "loupe: click the exact "
                                 "pixel, or Enter to accept the prediction as it is", before_open=offer)

    def walk_on(self, gid: str, client=None) -> str | None:
        """After an observation of `gid`: open the loupe in the next image of its group(s) that
        has none, at the GCP's predicted pixel there (from every observation so far); returns
        that image, or None when every image that can see it has an observation."""
        from recon_core.euclidean.gcp_transfer import predict_observation

        if not self.walk.value or gid not in self.app.session.ids:
            return None
        obs = self.app.session.get(gid).observations
        images = {im.name: im for im in self.app.site.images}
        order = [im.name for im in self.app.site.images]
        current = self.image.value
        start = order.index(current) + 1 if current in order else 0
        skipped = []
        for image in order[start:] + order[:start]:
            if image in obs:
                continue
            model = next((m for m in self.app.models.values() if image in m.images), None)
            if model is None or not any(im in model.images for im in obs):
                continue
            pred = predict_observation(model, images, obs, image)
            if pred is None:
                skipped.append(image)
                continue
            self.show_hint(gid, pred, client)
            return image
        n = len(obs)
        others = [g for g in self.app.session.ids if g != gid and not self.finished(g)]
        self.app.note(f"{gid} is observed in {n} image(s)"
                      + (f"; no registered tile of {', '.join(skipped)} sees it" if skipped else "")
                      + (": N for the next GCP" if others else
                         ": every GCP is placed in every image that sees it; press Upgrade (Results tab)"))
        return None

    def drop_prediction(self) -> None:
        if self.prediction is not None:
            self.prediction = None
            self.accept.disabled = True
            self.accept.label = "Accept the prediction"

    def _accept(self, client=None) -> None:
        if self.prediction is None:
            raise GcpError("no prediction to accept: press Predict first")
        gid, pred = self.prediction
        if self.app.picking.loupe is not None and not self.app.picking.owns_loupe(gid, client):
            raise GcpError(self.app.gcp.not_your_loupe(gid, client))
        self.drop_prediction()
        add_observation(self.app.session, gid, pred.image, pred.col, pred.row)
        in_loupe = self.app.picking.loupe is not None
        if in_loupe:
            self.app.picking.close_loupe(client)
        self.app.gcp.changed(select=gid, note=f"{gid}: observed in {pred.image} at col {pred.col:.2f}, "
                                               f"row {pred.row:.2f} (accepted prediction)")
        if in_loupe:
            self.walk_on(gid, client)

    def _undo(self) -> None:
        what = undo(self.app.session)
        self.app.gcp.changed(note=f"undone: {what}")

    def _redo(self) -> None:
        what = redo(self.app.session)
        self.app.gcp.changed(note=f"redone: {what}")

    # -- display --------------------------------------------------------------------------------
    def relabel(self, gid: str | None = None) -> None:
        """The list's entries (id, role, images placed) for the working set and the registered
        images as they are now, `gid` (default: the one chosen) shown as chosen; nothing else
        changes (the reconstruction registering images calls this alone)."""
        gid = (self.selected() or self.NEW) if gid is None else gid
        labels = {i: self.option_of(i) for i in self.app.session.ids}
        self._ids = {v: k for k, v in labels.items()}
        options = [self.NEW] + list(labels.values())
        current = labels.get(gid, self.NEW)
        if tuple(self.select.options) != tuple(options):
            self.select.options = options
        if self.select.value != current:
            self.select.value = current

    def refresh(self, select: str | None = "keep") -> None:
        s = self.app.session
        before = self.selected() or self.NEW
        self.relabel(before if select == "keep" else (select or self.NEW))
        if self._delete_armed is not None and self._delete_armed[0] != self.selected():
            self._disarm_delete()
        self.drop_prediction()             # any edit or selection change makes it stale
        u, r = can_undo(s), can_redo(s)
        self.undo.disabled, self.redo.disabled = u is None, r is None
        self.undo.label = f"Undo: {u}" if u else "Undo"
        self.redo.label = f"Redo: {r}" if r else "Redo"
        self.fill_fields(clear_new=before != self.NEW)
        self.listing.content = self.working_set_table()

    def fill_fields(self, clear_new: bool = True) -> None:
        """Show the selected GCP; for a new GCP, empty the fields (unless the operator was
        already typing into them: clear_new False)."""
        gid = self.selected()
        s = self.app.session
        g = s.get(gid) if gid is not None and gid in s.ids else None
        self.role_toggle.disabled = self.enable_toggle.disabled = g is None
        self.take_height.disabled = g is None or g.sigma_h_m is None
        if g is not None:
            self.role_toggle.label = "Make it a check point" if g.role == "control" else "Make it a control point"
            self.enable_toggle.label = "Disable it" if g.enabled else "Enable it"
        if gid is None or gid not in s.ids:
            self.info.content = (f"{len(s.gcps)} GCP(s) in the list "
                                 f"(`{s.path.name}` in the output folder). Type the new GCP's "
                                 "ground coordinates below before clicking its pixel.")
            if tuple(self.jump.options) != (self.JUMP_NONE,):
                self.jump.options = [self.JUMP_NONE]
            if clear_new:    # a new GCP never starts from the previous GCP's coordinates
                self.gid.value = ""
                self.role.value = "control"
                self.x.value, self.y.value, self.h.value = 0.0, 0.0, 0.0
            return
        g = s.get(gid)
        self.info.content = describe(g, self.residuals(gid))
        opts = [self.JUMP_NONE] + sorted(g.observations)
        if tuple(self.jump.options) != tuple(opts):
            self.jump.options = opts
        self.gid.value = g.id
        self.role.value = g.role
        self.crs.value = "lon, lat, h (WGS84)"
        self.x.value, self.y.value, self.h.value = g.lon, g.lat, g.h

    def working_set_table(self) -> str:
        """The working set at a glance (a marker list): each GCP's role, the registered images it
        is placed in, its error in metres from the last upgrade (E / N / U: a check point's
        residual; a control point's as predicted by the others when the fit has some to spare,
        marked *, else its residual in the fit) and its worst reprojection residual (px; where
        >= 2 observations give one), the selected one in bold."""
        s = self.app.session
        if not s.gcps:
            return "No GCP yet."
        images = self._registered_images()
        sel = self.selected()
        errors = upgrade_errors(self.app.gcp.upgrade)
        rows = ["| GCP | role | images | error E / N / U (m) | worst residual |", "|---|---|---|---|---|"]
        for g in s.gcps:
            res = self.residuals(g.id) if len(g.observations) >= 2 else {}
            worst = max(res.items(), key=lambda kv: kv[1], default=None)
            name = f"**{g.id}**" if g.id == sel else g.id
            role = g.role if g.enabled else f"{g.role}, off"
            placed = f"{len(set(g.observations) & images)} / {len(images)}"
            rows.append(f"| {name} | {role} | {placed} | {errors.get(g.id, '-')} | "
                        + ("-" if worst is None else f"{worst[1]:.2f} px ({worst[0]})") + " |")
        if any(v.endswith("*") for v in errors.values()):
            rows.append("\n\\* predicted by the other control GCPs (left out of the fit)")
        return "\n".join(rows)

    def set_regions(self, names: list[str]) -> None:
        opts = ["whole image"] + names
        if tuple(self.region.options) != tuple(opts):
            self.region.options = opts
            self.region.value = "whole image"
