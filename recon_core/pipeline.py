"""The orchestrator: runs the stages in order under OUT's lock, reloading what is done.

Each stage lives in its own module (STAGE_MODULES: run(state, bus) -> summary, load(state));
what a run checks before computing is recon_core.preflight's, what decides that a finished
stage can be reloaded is recon_core.resume's. OUT/report.json gathers every stage's summary and
is rewritten atomically after each stage.
"""

from __future__ import annotations

import json
import shutil
import time
import zipfile
from pathlib import Path
from typing import Sequence

from recon_core.config import Config
from recon_core.context import RunState, Stage
from recon_core.dense import stage as dense_stage
from recon_core.euclidean import dsm_stage, upgrade_stage
from recon_core.evaluation import stage as eval_stage
from recon_core.events import EventBus, Message, ModelsReady, StageDone, StageStarted
from recon_core.io.files import write_json
from recon_core.io.gcps import read_gcps_geojson, working_gcp_file
from recon_core.io.layout import OutLayout
from recon_core.io.lock import out_lock
from recon_core.io.site import Site
from recon_core.model.grouping import group_by_date
from recon_core.preflight import load_checked, make_out
from recon_core.resume import STAGES, config_hash, mark_done, stage_done
from recon_core.sparse import stage as sparse_stage


# stage name -> its module (a Stage: run(state, bus) -> summary, load(state))
STAGE_MODULES: dict[str, Stage] = {"sparse": sparse_stage, "dense": dense_stage, "upgrade": upgrade_stage,
                 "dsm": dsm_stage, "eval": eval_stage}
assert tuple(STAGE_MODULES) == STAGES      # resume's order is the one the stages run in


def _open(site_path, out, until, redo_from) -> tuple[Site, Path]:
    """The checked stage names, the loaded site and the output folder (created)."""
    site, out = load_checked(site_path, out, until, redo_from)
    return site, make_out(out)


def _remove(paths: list[Path]) -> None:
    for p in paths:
        if p.is_dir():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)


def run(site_path: str | Path, out: str | Path, cfg: Config | None = None, *,
        until: str | None = None, bus: EventBus | None = None, resume: bool = True,
        redo_from: str | None = None, wait: bool = False) -> RunState:
    """Run the pipeline on a site up to and including stage `until` (default: all).

    Finished stages are reloaded when `resume` (unless what they depend on changed);
    `redo_from` recomputes that stage and every later one. The run holds OUT's lock
    (recon_core.io.lock): another job on OUT is refused, or with `wait` waited for.
    """
    cfg = cfg or Config()
    bus = bus or EventBus()
    site, out = _open(site_path, out, until, redo_from)
    with out_lock(out, wait=wait, on_wait=lambda text: bus.emit(Message("warning", text))):
        return _run_locked(site, out, cfg, until, bus, resume, redo_from)


def _run_locked(site: Site, out: Path, cfg: Config, until, bus: EventBus, resume: bool,
                redo_from) -> RunState:
    lay = OutLayout(out)
    swept = lay.scratch()
    _remove(swept)                             # a dead job's leftovers (this job holds OUT's lock)
    if swept:
        bus.emit(Message("info", f"removed {len(swept)} scratch file(s) of an interrupted run from {out}"))
    gcp_path = working_gcp_file(site.root, out)
    gcp_text = gcp_path.read_text() if gcp_path.exists() else ""
    site_gcps = site.root / "gcps.geojson"
    if gcp_path != site_gcps and site_gcps.exists() and site_gcps.stat().st_mtime > gcp_path.stat().st_mtime:
        bus.emit(Message("warning", f"{site_gcps} changed after {gcp_path} was made: this run uses "
                                    f"{gcp_path} (the viewer's working set); delete it to use the site's"))
    gcps = site.gcps
    if gcp_path != site.root / "gcps.geojson":
        gcps = read_gcps_geojson(gcp_path, {im.name: im for im in site.images})
        bus.emit(Message("info", f"GCPs from {gcp_path} (the viewer's working set), not the site's file"))
    groups = group_by_date(site.images, cfg.grouping.max_gap_days, cfg.grouping.max_span_days)
    report = _read_report(lay.report, bus) if resume else {}
    report.update({"site": str(site.root.resolve()), "gcp_file": str(gcp_path.resolve()),
                   "config": cfg.to_dict(), "config_hash": config_hash(cfg),
                   "groups": [{"index": g.index, "images": [im.name for im in g.images],
                               "span_days": g.span_days} for g in groups]})
    state = RunState(site, out, cfg, groups, gcps=gcps, gcp_file=gcp_path, gcp_text=gcp_text,
                     report=report)
    first_redo = STAGES.index(redo_from) if redo_from else len(STAGES)
    last = STAGES.index(until) if until else len(STAGES) - 1
    for k, stage in enumerate(STAGES[: last + 1]):
        module = STAGE_MODULES[stage]
        if resume and k < first_redo and stage_done(out, stage, cfg, site, gcp_text) and _reload(module, state, stage, bus):
            bus.emit(Message("info", f"{stage}: already done, reloaded from {out}"))
            if stage not in report.setdefault("stages", {}):     # a report lost or cut short
                report["stages"][stage] = _recorded_summary(lay, stage)
                write_json(lay.report, report)
        else:
            first_redo = min(first_redo, k)      # what follows a recomputed stage is recomputed
            t0 = time.time()
            bus.emit(StageStarted(stage))
            summary = module.run(state, bus)
            summary["seconds"] = time.time() - t0
            mark_done(state, stage, summary)
            bus.emit(StageDone(stage, summary["seconds"], summary))
        if stage == "sparse":
            bus.emit(ModelsReady(dict(state.models)))
    if first_redo <= last:
        _drop_later_products(state, STAGES[last + 1:], f"{STAGES[first_redo]} was recomputed and the "
                             f"run stopped before {STAGES[last + 1] if last + 1 < len(STAGES) else 'the end'}", bus)
    else:
        # nothing recomputed, but an input of a later stage may have changed (the GCP file before
        # `--stage dense`): its products no longer match this run's inputs
        stale = [s for s in STAGES[last + 1:] if lay.stage_record(s).exists()
                 and not stage_done(out, s, cfg, site, gcp_text)]
        if stale:
            _drop_later_products(state, STAGES[STAGES.index(stale[0]):],
                                 f"an input of the {stale[0]} stage changed since it ran", bus)
    return state


def _read_report(path: Path, bus: EventBus) -> dict:
    """OUT/report.json as a resumed run extends it; unreadable (cut short, edited): started anew,
    saying so (the stages' own records decide what is reloaded)."""
    if not path.exists():
        return {}
    try:
        report = json.loads(path.read_text())
        if not isinstance(report, dict):
            raise ValueError("not a JSON object")
        return report
    except (OSError, ValueError) as exc:
        bus.emit(Message("warning", f"{path}: unreadable ({exc}); this run writes it anew"))
        return {}


def _recorded_summary(lay: OutLayout, stage: str) -> dict:
    """A finished stage's summary as its record keeps it (for a report.json made anew)."""
    try:
        return json.loads(lay.stage_record(stage).read_text()).get("summary", {})
    except (OSError, ValueError, AttributeError):
        return {}


# what a damaged product raises when a finished stage reloads it
RELOAD_ERRORS = (OSError, ValueError, KeyError, IndexError, EOFError, zipfile.BadZipFile)


def _reload(module, state: RunState, stage: str, bus: EventBus) -> bool:
    """Reload a finished stage's products; False (said) when they cannot be read: the stage is
    then computed again rather than the run failing on a damaged file."""
    try:
        module.load(state)
        return True
    except RELOAD_ERRORS as exc:
        bus.emit(Message("warning", f"{stage}: its saved products in {state.out} cannot be read "
                                    f"({type(exc).__name__}: {exc}); computing it again"))
        return False


def _drop_later_products(state: RunState, later: Sequence[str], why: str, bus: EventBus) -> None:
    """A run that recomputed `recomputed` and stopped before `later`: what those stages wrote
    came from other inputs (another site, other images, other GCPs): remove their products,
    records and report entries, so OUT holds only what this run's report describes."""
    lay = OutLayout(state.out)
    gone = []
    for stage in later:
        products = lay.stage_products(stage)
        _remove(products)
        gone += [p.name for p in products]
        lay.stage_record(stage).unlink(missing_ok=True)
        state.report.get("stages", {}).pop(stage, None)
    if gone:
        write_json(lay.report, state.report)
        bus.emit(Message("warning", f"{why}: removed what the later stages had written from "
                                    f"other inputs ({', '.join(gone)}); run them to make it again"))
