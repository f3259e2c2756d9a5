"""The GCP tab's actions: what its buttons, keys and list do to the working set, run on the
viewer's update thread. GcpPanel (gcp_panel.py) builds the widgets and wires them to these;
the actions read the widgets through `self` (GcpPanel is a GcpActions)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from recon_core.euclidean.gcp_transfer import FROM_SURVEY, place_in_other_images

from .gcp_session import (
    GcpError,
    add_observation,
    delete_gcp,
    edit_gcp,
    ground_to_llh,
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
from .results import image_group, predict_in, surveyed_in

if TYPE_CHECKING:
    from .gcp_panel import GcpPanelHost


class GcpActions:
    """The GCP tab's actions (a mixin of GcpPanel: its widgets and `app` are on self)."""

    if TYPE_CHECKING:                    # what GcpPanel puts on self (declared for the checker only)
        app: GcpPanelHost
        NEW: str
        CONFIRM_S: float
        chosen: dict[int, str]
        _ids: dict[str, str]
        # its widgets (viser GUI handles)
        image: Any
        select: Any
        catalogue: Any
        accept: Any
        delete: Any
        jump: Any
        walk: Any
        gid: Any
        role: Any
        crs: Any
        epsg: Any
        x: Any
        y: Any
        h: Any

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
        from .results import residual_vectors

        g = self.app.session.get(gid)
        return {im: float(np.hypot(*v)) for im, v in residual_vectors(self.app.models, g.observations).items()}

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
        gid = self.selected()
        if gid is None:
            raise GcpError("select a GCP first")
        image = self.image.value
        ref = getattr(self.app, "reference", None)
        if ref is not None and image == ref.ortho.name:
            raise GcpError("the reference orthoimage gives ground positions, not observations: click "
                           f"{gid}'s spot on it, or choose one of the site's images to predict in")
        g = self.app.session.get(gid)
        found = image_group(self.app.models, image)
        if found is None:
            raise GcpError(f"no registered model holds {image} yet (wait for the sparse stage)")
        pred = self.predict_shown(g, image)
        if pred is None:
            upgraded = surveyed_in(self.app.gcp.upgrade_maps(), found[0], g.llh) is not None
            raise GcpError(f"cannot predict {gid} in {image}: "
                           + ("its surveyed position falls outside every registered tile there; "
                              if upgraded else "") + "observe it in another image of its group first "
                           "(where a registered tile contains it)")
        self.prediction = (gid, pred)
        self.accept.disabled = False
        self.accept.label = f"Accept: {gid} at col {pred.col:.2f}, row {pred.row:.2f}"
        self.app.note(f"{gid} predicted in {image} at col {pred.col:.2f}, row {pred.row:.2f} "
                      f"({pred.how}; {pred.uncertainty()}); Accept records it, or click the right pixel")
        return pred

    def predict_shown(self, g, image: str):
        """The GCP g's prediction in `image` as the GCP tab shows it (results.predict_in, refined
        by matching): from its observations, or from its surveyed position once the image's
        group is upgraded and it has fewer than 2 observations there."""
        return predict_in(self.app.models, image, g.observations, g.llh, self.app.gcp.upgrade_maps(),
                          {im.name: im for im in self.app.site.images})

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
        # an image left to the operator shows what the GCP tab shows there: the prediction from
        # the surveyed position when the GCP still has fewer than 2 observations in that group
        obs = self.app.session.get(gid).observations
        for image in list(hints):
            shown = predict_in(self.app.models, image, obs, g.llh, self.app.gcp.upgrade_maps(), refine=False)
            if shown is not None and shown.source == FROM_SURVEY:
                hints[image] = shown
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
        has none, at the GCP's predicted pixel there (from every observation so far, or from its
        surveyed position once that image's group is upgraded: predict_shown); returns that
        image, or None when every image that can see it has an observation."""
        if not self.walk.value or gid not in self.app.session.ids:
            return None
        g = self.app.session.get(gid)
        obs = g.observations
        upgrade = self.app.gcp.upgrade_maps()
        order = [im.name for im in self.app.site.images]
        current = self.image.value
        start = order.index(current) + 1 if current in order else 0
        skipped = []
        for image in order[start:] + order[:start]:
            if image in obs:
                continue
            found = image_group(self.app.models, image)
            if found is None or not (any(im in found[1].images for im in obs)
                                     or surveyed_in(upgrade, found[0], g.llh) is not None):
                continue
            pred = self.predict_shown(g, image)
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

    def _undo(self) -> str:
        """Undo the latest edit (whoever made it: this page, another tab, the image workspace);
        returns what was undone."""
        what = undo(self.app.session)
        self.app.gcp.changed(note=f"undone: {what}")
        return what

    def _redo(self) -> str:
        what = redo(self.app.session)
        self.app.gcp.changed(note=f"redone: {what}")
        return what

