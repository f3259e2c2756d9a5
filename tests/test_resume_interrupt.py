"""Resume that can be trusted, and interruptions that leave nothing behind."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from recon_core.config import preset
from recon_core.io.layout import OutLayout
from recon_core.io.site import load_site
from recon_core.pipeline import run
from recon_core.resume import finished_stages

ROOT = Path(__file__).resolve().parents[1]


def _copy(state, tmp_path):
    site, out = tmp_path / "site", tmp_path / "out"
    shutil.copytree(state.site.root, site)
    shutil.copytree(state.out, out)
    return site, out


def test_changed_inputs_make_the_stages_stale(tiny_run, tmp_path):
    state, _ = tiny_run
    site, out = _copy(state, tmp_path)
    cfg = preset("tiny")
    assert finished_stages(out, cfg, load_site(site)) == set(finished_stages(state.out, cfg, state.site))
    assert "dsm" in finished_stages(out, cfg, load_site(site))
    # a touched image (same bytes, another modification time) is the same input
    img = sorted((site / "images").glob("*.tif"))[0]
    os.utime(img, ns=(img.stat().st_atime_ns, img.stat().st_mtime_ns + 10**9))
    assert "dsm" in finished_stages(out, cfg, load_site(site))
    # another image (same name, other bytes) makes everything stale
    data = bytearray(img.read_bytes())
    data[-1] ^= 0xFF
    img.write_bytes(bytes(data))
    assert finished_stages(out, cfg, load_site(site)) == set()
    # a changed site.json (resolution 0.5 -> 1.0) too: the DSM is not "already done" at 0.5 m
    site2, out2 = _copy(state, tmp_path / "b")
    doc = json.loads((site2 / "site.json").read_text())
    doc["resolution_m"] = 1.0
    (site2 / "site.json").write_text(json.dumps(doc))
    assert "dsm" not in finished_stages(out2, cfg, load_site(site2))


def test_a_partial_rerun_on_other_inputs_leaves_no_product_of_the_earlier_run(tiny_run, tmp_path):
    """The trial: `--stage sparse` from another site into a finished OUT rewrote report.json for
    the new site but left the old dense cloud, upgrade, DSM and evaluation (and their summaries)
    in place. Now the later stages' products, records and summaries go, with a warning."""
    from recon_core.events import EventBus, Message

    state, _ = tiny_run
    site, out = _copy(state, tmp_path)
    lay = OutLayout(out)
    assert lay.dsm.exists() and lay.dense_ply(0).exists()
    msgs = []
    run(site, out, preset("tiny"), until="sparse", resume=False,
        bus=EventBus(lambda ev: msgs.append(ev) if isinstance(ev, Message) else None))
    report = json.loads(lay.report.read_text())
    assert set(report["stages"]) == {"sparse"}
    assert not any(lay.stage_products(s) for s in ("dense", "upgrade", "dsm", "eval"))
    assert not lay.stage_record("dsm").exists() and lay.cameras(0).exists()
    assert any(m.level == "warning" and "dsm.tif" in m.text for m in msgs), [m.text for m in msgs]
    # resuming a finished run without recomputing anything removes nothing
    site2, out2 = _copy(state, tmp_path / "b")
    run(site2, out2, preset("tiny"), until="sparse")
    assert OutLayout(out2).dsm.exists()


def test_a_rerun_sweeps_an_interrupted_runs_scratch(tiny_run, tmp_path):
    state, _ = tiny_run
    site, out = _copy(state, tmp_path)
    lay = OutLayout(out)
    junk = [out / ".dsm.tif.ab12cd34.tif", out / ".cloud.ply.zz_9yy88.ply", out / ".dsm.tif.q9w8e7r6.tif.ovr.tmp",
            lay.group_dir(0) / ".dense.ply.k3j4h5g6.ply"]
    for j in junk:
        j.write_bytes(b"partial")
    (lay.group_dir(0) / ".dense_parts_x1y2z3w4").mkdir()
    (out / "dsm_blocks_q1w2e3r4").mkdir()
    (out / ".dsm_work_a1s2d3f4").mkdir()
    (out / ".sparse_desc_z8x7c6v5").mkdir()
    (out / ".keepme").write_text("a user's file")
    assert len(lay.scratch()) == 8
    run(site, out, preset("tiny"))                            # every stage reloaded
    assert lay.scratch() == [] and (out / ".keepme").exists() and lay.dsm.exists()


def _children_of(pid: int) -> set[int]:
    out = set()
    for p in Path("/proc").iterdir():
        if p.name.isdigit():
            try:
                st = (p / "stat").read_text()
            except OSError:
                continue
            if int(st.rsplit(")", 1)[1].split()[1]) == pid:
                out.add(int(p.name))
    return out


def _descendants_of(pid: int) -> set[int]:
    """Every process below pid: the forkserver and the resource tracker (its children), and the
    pool workers (the forkserver's children)."""
    out, todo = set(), [pid]
    while todo:
        kids = _children_of(todo.pop()) - out
        out |= kids
        todo += list(kids)
    return out


def _alive(pid: int) -> bool:
    try:
        st = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return st.rsplit(")", 1)[1].split()[0] != "Z"


def test_pool_workers_end_when_the_main_process_is_killed(tmp_path):
    """kill -9 of the process that owns the pool: its workers, the forkserver and the resource
    tracker all end by themselves (no orphan holds memory after a killed run)."""
    code = ("import os, sys, time\n"
            "from recon_core.dense.executor import LocalExecutor\n"
            "ex = LocalExecutor(2)\n"
            "pids = sorted({f.result() for f in [ex.pool.submit(os.getpid) for _ in range(40)]})\n"
            "print(' '.join(map(str, pids)), flush=True)\n"
            "time.sleep(120)\n")
    p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    pids = [int(x) for x in p.stdout.readline().split()]
    assert pids and all(_alive(w) for w in pids)
    family = _descendants_of(p.pid)
    assert set(pids) < family and len(family) >= len(pids) + 1      # + the forkserver (+ tracker)
    os.kill(p.pid, signal.SIGKILL)
    p.wait()
    deadline = time.time() + 15
    while any(_alive(w) for w in family) and time.time() < deadline:
        time.sleep(0.2)
    left = sorted(w for w in family if _alive(w))
    assert not left, f"outlived their process: {[Path(f'/proc/{w}/cmdline').read_bytes()[:80] for w in left]}"


def test_sigterm_ends_a_run_like_ctrl_c_and_leaves_no_scratch(tiny_site, tmp_path):
    out = tmp_path / "out"
    p = subprocess.Popen([sys.executable, "-m", "recon_core.cli", "run", str(tiny_site), "--out", str(out),
                          "--preset", "tiny", "--quiet", "--workers", "2"],
                         stderr=subprocess.PIPE, text=True, cwd=ROOT)
    deadline = time.time() + 180
    while not (out / "stages" / "sparse.json").exists():     # dense is running next
        assert p.poll() is None and time.time() < deadline, p.stderr.read() if p.poll() else "too slow"
        time.sleep(0.1)
    time.sleep(1.0)
    kids = _descendants_of(p.pid)
    p.send_signal(signal.SIGTERM)
    try:
        rc = p.wait(60)
    except subprocess.TimeoutExpired:
        p.kill()
        pytest.fail("SIGTERM did not end the run")
    err = p.stderr.read()
    assert rc == 130 and "interrupted" in err and "Traceback" not in err, err
    assert OutLayout(out).scratch() == []
    deadline = time.time() + 15
    while any(_alive(k) for k in kids) and time.time() < deadline:
        time.sleep(0.2)
    assert not any(_alive(k) for k in kids), "processes outlived the run"
