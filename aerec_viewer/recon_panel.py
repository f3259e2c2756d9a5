"""The Reconstruction tab: the run's status, progress and figures, the display controls, the
messages, and what the display draws while a view moves (motion.py). The viewer (app.ViewerApp)
owns the scene and calls `update` from its update thread."""

from __future__ import annotations

from typing import TYPE_CHECKING

from .display import COLOR_MODES
from .scene import TILE_MODES

if TYPE_CHECKING:
    from .app import ViewerApp
    from .worker import DisplaySnapshot


class ReconstructionPanel:
    """The Reconstruction tab's widgets (g_*) and what drives them."""

    def __init__(self, app: "ViewerApp", gui):
        self.app = app
        self._motion_said = False
        self.g_title = gui.add_markdown(f"### AE-Rec · {self.app.site.name}")
        self.g_status = gui.add_markdown("starting…")
        self.g_progress = gui.add_progress_bar(0.0, animated=True)
        self.g_stats = gui.add_markdown("")
        self.g_frame = gui.add_markdown("")
        self.g_pause = gui.add_button("Pause", hint="pauses the reconstruction at its next step")
        with gui.add_folder("Display"):
            self.g_size = gui.add_slider("Point size", 0.1, 5.0, 0.1, 1.0)
            self.g_color = gui.add_dropdown("Colour by", list(COLOR_MODES),
                                            initial_value=self.app.scene.settings.color_mode)
            self.g_budget = gui.add_slider("Point budget (k)", 10, 2000, 10,
                                           self.app.scene.settings.budget // 1000,
                                           hint="points displayed at most when the view rests (fewer "
                                                "while it moves, as the page's frame rate asks); "
                                                "the full cloud stays on disk")
            self.g_budget_note = gui.add_markdown("")
            self.g_tiles = gui.add_dropdown(
                "Tiles", list(TILE_MODES), initial_value=self.app.scene.settings.tiles,
                hint="; ".join(f"{k}: {v}" for k, v in TILE_MODES.items())
                + " (textured tiles are slow to draw without a GPU)")
            self.g_sparse = gui.add_checkbox("Sparse points", True)
            self.g_dense = gui.add_checkbox("Dense points", True)
            self.g_reset = gui.add_button("Reset view")
        self.g_messages = gui.add_markdown("")
        self._wire()

    def _wire(self) -> None:
        app = self.app
        s = app.scene.settings
        sub = app.submit

        def setter(fn):
            return lambda _: sub(fn)

        self.g_pause.on_click(setter(self.toggle_pause))
        self.g_size.on_update(setter(lambda: (setattr(s, "point_size", float(self.g_size.value)),
                                              self.app.scene.apply_point_size())))
        self.g_color.on_update(setter(lambda: (setattr(s, "color_mode", self.g_color.value),
                                               self.app.scene.apply_colors())))
        self.g_budget.on_update(setter(lambda: (setattr(s, "budget", int(self.g_budget.value) * 1000),
                                                self.app.force())))
        self.g_tiles.on_update(setter(lambda: (setattr(s, "tiles", self.g_tiles.value),
                                               self.app.scene.set_tiles_visible(self.g_tiles.value != "hidden"),
                                               self.app.force())))
        self.g_sparse.on_update(setter(lambda: (setattr(s, "show_sparse", self.g_sparse.value),
                                                self.app.scene.apply_visibility())))
        self.g_dense.on_update(setter(lambda: (setattr(s, "show_dense", self.g_dense.value),
                                               self.app.scene.apply_visibility(), self.app.force())))
        self.g_reset.on_click(lambda ev: sub(lambda: self.app.views.frame_client(ev.client)))

    def said_motion(self, text: str, lowered: bool) -> None:
        """What the moving display became (motion.py): under the budget slider, and once in the
        messages the first time it is thinned (a slow page would otherwise fill them)."""
        self.g_budget_note.content = text
        if lowered and not self._motion_said:
            self._motion_said = True
            self.app.worker.message(text + " (Display)", "info")

    def update(self, snap: DisplaySnapshot) -> None:
        done = ("affine reconstruction finished: **place the control GCPs** (GCPs tab), then Upgrade"
                if snap.awaiting_gcps else "finished")
        status = {"running": "running", "paused": "**paused**", "done": done,
                  "reopened": "reopened (nothing recomputed)", "failed": "**failed**",
                  "stopped": "stopped", "starting": "starting"}.get(snap.status, snap.status)
        stage = ""
        if snap.stage and snap.status not in ("done", "reopened", "stopped"):
            grp = "" if snap.stage_group is None else f" [group {snap.stage_group}]"
            stage = f" · stage **{snap.stage}**{grp}"
            if snap.stage_total:
                stage += f" {snap.stage_done}/{snap.stage_total}"
            if snap.stage_message:
                stage += f" · {snap.stage_message}"
        if snap.status == "failed" and snap.failed_stage:
            status = f"**failed in the {snap.failed_stage} stage**"
            stage = ""
        text = f"{status}{stage}"
        if snap.error:
            text += f"\n\n**Error:** {snap.error}"
        if snap.hint:
            text += f"\n\n*What to do:* {snap.hint}"
        self.app.set_md(self.g_status, text)
        if snap.stage_total:
            self.g_progress.value = float(100.0 * snap.stage_done / snap.stage_total)
        done = snap.status in ("done", "reopened", "failed", "stopped")
        if done:
            self.g_progress.value = 100.0
        self.g_progress.animated = not done and snap.status != "paused"
        self.g_pause.label = "Resume" if snap.status == "paused" else "Pause"
        self.g_pause.disabled = done
        self.app.set_md(self.g_stats, self.stats_md(snap))
        label = next((T.label for T in self.app.transforms(snap).values() if T is not None), "")
        self.app.set_md(self.g_frame, f"*Frame:* {label}" if label else "")
        msgs = [m for m in snap.messages if m[0] != "debug"][-6:]
        self.app.set_md(self.g_messages, "\n".join(f"- {lvl}: {txt}" for lvl, txt in msgs))

    def stats_md(self, snap: DisplaySnapshot) -> str:
        rows = ["| | |", "|---|---:|"]
        for g, gs in sorted(snap.groups.items()):
            pre = f"g{g} " if len(snap.groups) > 1 else ""
            rows.append(f"| {pre}tiles registered | {len(gs.tiles)} / {gs.total_tiles} |")
            rows.append(f"| {pre}sparse points | {gs.sparse.n:,} |")
            if gs.dense.n:
                thin = "" if gs.dense.kept_fraction >= 1 else f" (kept 1/{1 / gs.dense.kept_fraction:.0f})"
                rows.append(f"| {pre}dense points | {gs.dense.n:,}{thin} |")
            if gs.ba:
                rows.append(f"| {pre}reprojection RMS (last BA) | {gs.ba['rms_px']:.3f} px |")
                rows.append(f"| {pre}BA cost ({gs.ba['scope']}) | {gs.ba['cost_before']:.4g} → "
                            f"{gs.ba['cost_after']:.4g} |")
        rows.append(f"| points displayed | {self.app.scene.displayed_points():,} |")
        for k, v in snap.stages_finished.items():
            rows.append(f"| {k} done | {v:.1f} s |")
        return "\n".join(rows)

    def toggle_pause(self) -> None:
        if self.app.worker.paused:
            self.app.worker.resume()
        else:
            self.app.worker.pause()
