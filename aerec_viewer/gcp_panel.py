"""The GCP tab: its widgets and what they do. The edits themselves are gcp_session's; the
picking plane and its loupe, where a click becomes a pixel, are the picking view's (picking)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable, Protocol

from .gcp_actions import GcpActions
from .gcp_session import (
    ROLES,
    GcpError,
    GcpSession,
    can_redo,
    can_undo,
    default_epsg,
    describe,
    nudge_observation,
)
from .picking import PickingView

if TYPE_CHECKING:
    from recon_core.io.site import Site

    from .gcp_controller import GcpController


def upgrade_errors_m(outcome) -> dict[str, tuple[float, float, float, bool]]:
    """GCP id -> (dE, dN, dU in metres, left out) from an upgrade's rows (the first group that
    scores it): a control point's leave-one-out error (left out: True) where there is one, else
    its residual (a check point's is always its error, the fit never saw it)."""
    out: dict[str, tuple[float, float, float, bool]] = {}
    if outcome is None:
        return out
    for g in sorted(outcome.results):
        for p in outcome.results[g].points:
            if p["id"] in out or p.get("dU") is None:
                continue
            loo = p.get("loo_dU") is not None and p["role"] == "control"
            e, n, u = (float(p[f"loo_d{a}"] if loo else p[f"d{a}"]) for a in "ENU")
            out[p["id"]] = (e, n, u, loo)
    return out


def upgrade_errors(outcome) -> dict[str, str]:
    """GCP id -> "dE / dN / dU" (m) of upgrade_errors_m, a leave-one-out error marked *."""
    return {gid: f"{e:+.2f} / {n:+.2f} / {u:+.2f}" + ("*" if loo else "")
            for gid, (e, n, u, loo) in upgrade_errors_m(outcome).items()}


def workspace_link_html(url: str) -> str:
    """The GCP tab's link to the image workspace (a new browser tab: this page stays open)."""
    return (f'<div style="padding: 0 0.75rem 0.5rem; font-size: 0.875rem"><a href="{url}" target="_blank" '
            f'rel="noopener" style="font-weight: 600">Open the image workspace</a> ({url}): the selected '
            "GCP side by side in every image; drag to pan, the wheel zooms at the cursor, a click places "
            "it; each browser tab keeps its own selection</div>")


class GcpPanelHost(Protocol):
    """What the GCP tab needs of the viewer: the working set, the site, a way to run work on the
    update thread, and the scene actions its buttons trigger."""

    session: GcpSession
    site: Site
    models: dict                      # group -> SparseModel once the sparse stage is done

    picking: PickingView               # the picking plane and its loupe
    gcp: GcpController                 # the clicks, the working set's edits, the upgrade

    def submit(self, fn: Callable[[], object]) -> object: ...
    def note(self, text: str, level: str = "info") -> None: ...


# -- the panel --------------------------------------------------------------------------------
class GcpPanel(GcpActions):
    """Widgets of the GCP tab. Callbacks queue work on the app's update thread."""

    NEW = "(new GCP from the fields below)"
    CONFIRM_S = 10.0          # a second press of Delete within this time confirms

    def __init__(self, app: GcpPanelHost, gui):
        self.app = app
        s = app.session
        names = sorted(s.images)
        self.last_site_image = names[0]
        ref = getattr(app, "reference", None)
        # the latest prompt or warning, first: at 1000 px it sat below the fold, under the buttons
        self.status = gui.add_markdown("")
        ws = getattr(app, "workspace", None)
        self.workspace_link = None if ws is None else gui.add_html(workspace_link_html(ws.url))
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
