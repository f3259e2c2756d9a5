"""Benchmark of the synthetic site generator.

Prints the generation time (per stage) of the `tiny` and `demo` presets (`large` with
--large), the RPC fit residuals, and the affine-approximation error against tile size for the
images of the demo and large presets (geometry only: the large cameras are built without
rendering unless --large is given).

    python bench/bench_synth.py [--large] [--out DIR] [--seed N] [--previews DIR]
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from recon_core.synthetic import generator as syn  # noqa: E402


def _progress():
    state = {"t0": time.perf_counter(), "last": None}

    def cb(stage, done, total):
        if stage != state["last"]:
            state["last"] = stage
            print(f"    {time.perf_counter() - state['t0']:7.1f}s  {stage}", flush=True)
    return cb


def generate(preset: str, out: Path, seed: int) -> syn.SynthTruth:
    site = out / f"site_{preset}"
    if site.exists():
        shutil.rmtree(site)
    print(f"== generate {preset} -> {site}")
    t0, c0 = time.perf_counter(), time.process_time()
    truth = syn.generate_site(site, preset, seed=seed, progress=_progress())
    dt, dc = time.perf_counter() - t0, time.process_time() - c0
    P = truth.preset
    npx = sum(c.width * c.height for c in truth.cameras.values())
    print(f"  {preset}: {len(truth.cameras)} images, {npx / 1e6:.1f} Mpx, ss={P.supersample}: "
          f"{dt:.1f} s wall, {dc:.1f} s CPU  "
          f"({', '.join(f'{k} {v:.1f}s' for k, v in truth.timings.items())})")
    for name, info in truth.images.items():
        print(f"    {name} group {info['group']} {info['acquired']} {info['width']}x{info['height']} "
              f"off-nadir {info['off_nadir_deg']:.1f} deg, view az {info['view_azimuth_deg']:.0f}, "
              f"scan az {info['scan_azimuth_deg']:.0f}, sun el {info['sun_elevation']:.1f} "
              f"az {info['sun_azimuth']:.0f}")
    bh = json.loads((site / "truth" / "images.json").read_text())["base_to_height"]
    print("    B/H: " + ", ".join(f"{k} {v:.2f}" for k, v in bh.items()))
    print(f"    RPC fit: max {truth.rpc_fit['max_px']:.4f} px, RMS {truth.rpc_fit['rms_px']:.4f} px; "
          f"{len(truth.gcps)} GCPs ({sum(g['role'] == 'check' for g in truth.gcps)} check)")
    return truth


def affine_curve(preset: str, seed: int, sizes=(250, 500, 1000, 2000, 4000)) -> None:
    scene, cams = syn.design_cameras(preset, seed)
    print(f"== affine approximation error vs tile size ({preset}, max / mean of per-tile max, px)")
    for name, cam in cams.items():
        ss = [s for s in sizes if s < max(cam.width, cam.height)]
        err = syn.affine_error_vs_tile_size(cam, scene, sizes=ss, max_tiles=36)
        row = "  ".join(f"{s}: {e['max_px']:.3f}/{e['mean_max_px']:.3f}" for s, e in err.items())
        print(f"  {name} {cam.width}x{cam.height} off-nadir {cam.off_nadir_deg():4.1f}: {row}")


def save_previews(site: Path, out: Path, max_side: int = 1000) -> list[Path]:
    """8-bit percentile-stretched, downscaled images and a colourised GT DSM as PNG."""
    import cv2
    import rasterio

    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for tif in sorted((site / "images").glob("*.tif")):
        with rasterio.open(tif) as ds:
            f = max(1, int(np.ceil(max(ds.width, ds.height) / max_side)))
            a = ds.read(1, out_shape=(ds.height // f, ds.width // f),
                        resampling=rasterio.enums.Resampling.average).astype(float)
        lo, hi = np.percentile(a, [0.5, 99.5])
        p = out / f"{site.name}_{tif.stem}.png"
        cv2.imwrite(str(p), np.clip((a - lo) / (hi - lo) * 255, 0, 255).astype(np.uint8))
        paths.append(p)
    with rasterio.open(site / "gt_dsm.tif") as ds:
        f = max(1, int(np.ceil(max(ds.width, ds.height) / max_side)))
        d = ds.read(1)[::f, ::f]
        nodata = ds.nodata
    valid = d != nodata
    lo, hi = np.percentile(d[valid], [1, 99.5])
    img = np.clip((d - lo) / (hi - lo) * 255, 0, 255).astype(np.uint8)
    col = cv2.applyColorMap(img, cv2.COLORMAP_VIRIDIS)
    col[~valid] = 0
    p = out / f"{site.name}_gt_dsm.png"
    cv2.imwrite(str(p), col)
    paths.append(p)
    return paths


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--large", action="store_true", help="also generate the large preset")
    ap.add_argument("--out", type=Path, default=Path("/tmp/aerec_bench_synth"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--presets", nargs="*", default=None, help="presets to generate")
    ap.add_argument("--previews", type=Path, default=None, help="write PNG previews here")
    args = ap.parse_args()
    presets = args.presets if args.presets is not None else (
        ["tiny", "demo"] + (["large"] if args.large else []))
    args.out.mkdir(parents=True, exist_ok=True)
    for p in presets:
        generate(p, args.out, args.seed)
        if args.previews:
            for q in save_previews(args.out / f"site_{p}", args.previews):
                print(f"    preview {q}")
    affine_curve("demo", args.seed)
    affine_curve("large", args.seed)


if __name__ == "__main__":
    main()
