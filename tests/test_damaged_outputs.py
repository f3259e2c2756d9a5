"""An output folder whose products were deleted, replaced or damaged after a run: the next run
makes them again (saying why), never reports them as there, never stops on a traceback."""

from __future__ import annotations

import shutil

from recon_core.config import preset
from recon_core.events import EventBus, Message, StageStarted
from recon_core.io.layout import OutLayout
from recon_core.pipeline import run


def _run(site, out):
    events = []
    run(site, out, preset("tiny"), bus=EventBus(events.append))
    started = [e.stage for e in events if isinstance(e, StageStarted)]
    said = [e.text for e in events if isinstance(e, Message)]
    return started, said


def test_deleted_damaged_or_replaced_products_are_made_again(tiny_run, tmp_path):
    state, _ = tiny_run
    out = tmp_path / "out"
    shutil.copytree(state.out, out, ignore=shutil.ignore_patterns(".aerec.lock"))
    lay = OutLayout(out)
    assert _run(state.site.root, out)[0] == []                      # all there: all reloaded
    lay.dsm.unlink()
    started, _ = _run(state.site.root, out)
    assert started == ["dsm", "eval"] and lay.dsm.exists()
    lay.dsm.write_bytes(lay.dsm.read_bytes()[: lay.dsm.stat().st_size // 2])   # replaced (cut short)
    assert _run(state.site.root, out)[0] == ["dsm", "eval"]
    obs = lay.observations(0)
    obs.write_bytes(obs.read_bytes()[:100])                          # damaged, same name
    started, said = _run(state.site.root, out)
    assert started[0] == "sparse"
    lay.report.write_text(lay.report.read_text()[:100])              # cut short
    started, said = _run(state.site.root, out)
    assert started == [] and any("report.json: unreadable" in t for t in said)
    assert "stages" in __import__("json").loads(lay.report.read_text())


def test_a_damaged_ground_truth_is_refused_before_the_compute(tiny_site, tmp_path, capsys):
    """A ground truth cut short opens (its header is whole) but cannot be read: refused by the
    pre-flight, naming it, before any stage runs; `aerec eval` says the same in one line."""
    from recon_core.cli import main

    site = tmp_path / "site"
    shutil.copytree(tiny_site, site)
    gt = site / "gt_dsm.tif"
    gt.write_bytes(gt.read_bytes()[:3000])
    assert main(["run", str(site), "--out", str(tmp_path / "out"), "--preset", "tiny", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "gt_dsm.tif" in err[0] and "truncated or damaged" in err[0], err
    assert not (tmp_path / "out" / "stages").exists()
    assert main(["eval", str(tiny_site / "gt_dsm.tif"), str(gt), "--out", str(tmp_path / "ev")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "gt_dsm.tif" in err[0], err
    assert not (tmp_path / "ev").exists()                    # the folder it made, removed again


def test_eval_shift_info_grouping_and_synth_paths_out_of_reach_are_one_line(tiny_site, tmp_path, capsys):
    from recon_core.cli import main

    gt = str(tiny_site / "gt_dsm.tif")
    for shift in ("nan", "inf", "1e9", "-1"):
        assert main(["eval", gt, gt, "--max-shift", shift]) == 2, shift
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "--max-shift" in err[0], err
    for gap in ("nan", "-1"):
        assert main(["info", str(tiny_site), "--max-gap-days", gap]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "--max-gap-days" in err[0], err
    (tmp_path / "afile").write_text("x")
    assert main(["synth", str(tmp_path / "afile" / "x"), "--preset", "tiny", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "afile" in err[0] and "is a file" in err[0], err
