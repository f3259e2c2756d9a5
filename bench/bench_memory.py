"""The pre-flight's memory estimate of every stage against the measured peak. Prints a table;
asserts nothing.

    python bench/bench_memory.py --preset demo
    python bench/bench_memory.py --preset tiny --resolution 0.02      # a large DSM grid
    python bench/bench_memory.py --site ../shared/data/omaha_3dates

Runs the whole pipeline on the site (generated under --root for a preset) into a fresh OUT and
samples, every 0.1 s, the anonymous memory (RssAnon: what the machine must have; pages of
memory-mapped files, which the kernel can drop, are not counted) of this process and all its
descendants (the dense workers), per stage. `--resolution` sets the DSM's cell size
(a finer DSM grid: the DSM and evaluation stages' allocations grow with it); the stages before the
DSM are resumed from an earlier run of the same site (only the DSM and evaluation are measured
again). The estimate is
recon_core.memory.estimate's, which the pre-flight compares with the memory available.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from recon_core.config import preset as make_preset  # noqa: E402
from recon_core.events import EventBus, StageDone, StageStarted  # noqa: E402


def _children() -> dict[int, list[int]]:
    kids: dict[int, list[int]] = {}
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/stat") as f:
                ppid = int(f.read().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        kids.setdefault(ppid, []).append(int(d))
    return kids


def _anon_mb(pid: int) -> float:
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("RssAnon:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return 0.0


def tree_anon_mb(root: int) -> float:
    """RssAnon of `root` and every process below it (MB)."""
    kids, todo, total = _children(), [root], 0.0
    while todo:
        p = todo.pop()
        total += _anon_mb(p)
        todo += kids.get(p, [])
    return total


class TreePeak:
    """The peak of tree_anon_mb(this process) since the last take(), sampled every 0.1 s."""

    def __init__(self):
        self.since = 0.0
        threading.Thread(target=self._run, daemon=True).start()

    def _run(self):
        while True:
            self.since = max(self.since, tree_anon_mb(os.getpid()))
            time.sleep(0.1)

    def take(self) -> float:
        """The peak since the last call, the present value included (a stage holding the GIL may
        leave the sampler no chance to run)."""
        v, self.since = max(self.since, tree_anon_mb(os.getpid())), 0.0
        return v


def finer_gt(src: Path, dst: Path, res: float) -> None:
    """The ground truth on a grid of res-metre cells (nearest: the same heights, more cells)."""
    import rasterio
    from rasterio.enums import Resampling

    with rasterio.open(src) as ds:
        f = ds.transform.a / res
        shape = (int(ds.height * f), int(ds.width * f))
        z = ds.read(1, out_shape=shape, resampling=Resampling.nearest)
        prof = ds.profile
    prof.update(width=shape[1], height=shape[0], transform=ds.transform * ds.transform.scale(1 / f, 1 / f),
                tiled=True, blockxsize=256, blockysize=256, compress="deflate")
    dst.unlink(missing_ok=True)
    with rasterio.open(dst, "w", **prof) as out:
        out.write(z, 1)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--preset", default=None, help="a synthetic preset (generated under --root)")
    ap.add_argument("--site", type=Path, default=None)
    ap.add_argument("--tile-size", type=int, default=None)
    ap.add_argument("--resolution", type=float, default=None, help="the DSM's cell size (dsm.resolution_m)")
    ap.add_argument("--gt-resolution", type=float, default=None,
                    help="the ground truth resampled to this cell size (a large evaluation grid)")
    ap.add_argument("--root", type=Path, default=Path("/tmp/aerec_memory"))
    args = ap.parse_args(argv)
    from recon_core.io.site import load_site
    from recon_core.memory import estimate
    from recon_core.pipeline import run

    args.root.mkdir(parents=True, exist_ok=True)
    if args.site is None:
        from recon_core.synthetic.generator import generate_site

        src = args.root / f"{args.preset}_s0"
        if not (src / "site.json").exists():
            generate_site(src, preset=args.preset, seed=0)
    else:
        src = args.site
    site = src
    if args.gt_resolution is not None:      # a copy with a finer ground truth
        site = args.root / f"{src.name}_gt{args.gt_resolution}"
        if not site.exists():
            shutil.copytree(src, site, symlinks=True)
            finer_gt(src / "gt_dsm.tif", site / "gt_dsm.tif", args.gt_resolution)
    cfg = make_preset("tiny" if (args.preset or "").startswith("tiny") else "default")
    if args.tile_size:
        cfg = cfg.with_overrides({"tiling.tile_size": args.tile_size})
    if args.resolution:
        cfg = cfg.with_overrides({"dsm.resolution_m": args.resolution})
    est = {e.stage: e for e in estimate(load_site(site), cfg)}
    out = args.root / f"out_{site.name}"           # the stages before the DSM are kept and resumed
    peaks: dict[str, float] = {}
    meter = TreePeak()

    def on(ev):
        if isinstance(ev, StageStarted):
            meter.take()
        elif isinstance(ev, StageDone):
            peaks[ev.stage] = meter.take()
    t0 = time.time()
    run(site, out, cfg, bus=EventBus(on), redo_from="dsm" if (out / "stages").is_dir() else None)
    print(f"{site.name}: whole run {time.time() - t0:.0f} s")
    print("| stage | estimate (MB) | what drives it | measured peak (MB) | estimate / measured |")
    print("|---|---|---|---|---|")
    for stage, e in est.items():
        m = peaks.get(stage)
        ratio = f"{e.mb / m:.2f}" if m else "-"
        print(f"| {stage} | {e.mb:.0f} | {e.what} | {'-' if m is None else f'{m:.0f}'} | {ratio} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
