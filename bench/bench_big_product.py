"""Full-size products: peak memory of `aerec site init`, `aerec info` and the sparse stage's
feature extraction on two synthetic 40,000 x 40,000 px products that cost almost no disk.
Prints figures and a PASS/FAIL line per step against a memory budget; asserts nothing else.

    python bench/bench_big_product.py                       # builds under /tmp/aerec_bench/big
    python bench/bench_big_product.py --rows 1,2            # features on 1, then 2 block rows
    python bench/bench_big_product.py --size 20000 --rows 1 --budget-gib 1

The products (built once under --root): one textured tile of `--tile` px (a mirrored mosaic of
this project's demo image, or of `--tile-from IMAGE`: a real texture, so SIFT finds what it
finds on a scene) is repeated to `--size` px a side:

* product A, Pleiades-like: a DIMAP folder, DIM_*.XML (IMAGING_DATE / IMAGING_TIME) beside
  (size / tile)^2 tiles IMG_..._R<r>C<c>.TIF that are all links to the one tile file;
* product B: one VRT mosaicking an affinely warped copy of the tile (rotated 3 degrees, scaled
  0.97: another view), georeferenced (UTM, 0.5 m) and with TIFFTAG_DATETIME in its metadata.

Steps, each in its own process, each with its wall time and its peak memory (the RSS
high-water mark of the process, from wait4's rusage):

1. `aerec site init SITE A B`;
2. `aerec info SITE` (which also computes the group's tone curves, as `aerec run` would);
3. the sparse stage's feature extraction (`recon_core.sparse.stage`'s own calls: the group's
   tone curves from the images' overviews, then `detect_image` per image in threads, the
   descriptors written to the scratch folder as they are detected) over the top `--rows` block rows of each image (all 40,000
   columns; a block is FeatureConfig.detect_block px). All 20 block rows of both images is
   2 x 1,600 Mpx of SIFT: more than an hour per image on one core of the project's machine,
   hence a strip, and one strip height more (`--rows 1,2`) to measure how memory grows with
   the keypoints;
4. the coarse overview features (`detect_overview` at the stage's factor: the sparse stage
   computes them before matching).

The budget is on each step's peak. Feature extraction holds each image's keypoints (positions,
sizes, responses, intensities: 25 bytes each) for matching, so its peak grows with the keypoints
found; the bench gives that growth per keypoint from the two strips and extrapolates the peak
of whole images from it (a slope worth reading on strips of many blocks, as at 40,000 px; on a
product of a few blocks it is the noise of SIFT's working set). Its fixed part is SIFT's pyramid of one block, ~1 GB per feature
thread. The products' one tile stays in GDAL's block cache: reading is faster than a real
product's. Figures: docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

DIMAP = """<?xml version="1.0" encoding="UTF-8"?>
<Dimap_Document>
 <Dataset_Sources><Source_Identification><Strip_Source>
  <MISSION>PHR</MISSION><MISSION_INDEX>1A</MISSION_INDEX>
  <IMAGING_DATE>2024-03-02</IMAGING_DATE><IMAGING_TIME>10:41:07.5Z</IMAGING_TIME>
 </Strip_Source></Source_Identification></Dataset_Sources>
</Dimap_Document>
"""
STEM_A = "PHR1A_P_202403021041075_SEN_BIG"


def vm_hwm_mb() -> float:
    """This process's RSS high-water mark (VmHWM), MB."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


# -- the products ---------------------------------------------------------------------------
def _texture(src: Path | None, tile: int):
    """A tile x tile uint16 texture: the source image mirrored around itself as often as needed
    (the seams are mirror lines, not cuts), and an affinely warped copy of it (another view)."""
    import cv2
    import numpy as np
    import rasterio

    src = src or REPO / "assets" / "demo_site" / "images" / "img_00.tif"
    with rasterio.open(src) as ds:
        a = ds.read(1).astype(np.float32)
    while a.shape[0] < tile + 64 or a.shape[1] < tile + 64:
        a = np.block([[a, a[:, ::-1]], [a[::-1], a[::-1, ::-1]]])
    a = a[:tile + 64, :tile + 64]
    m = cv2.getRotationMatrix2D(((tile + 64) / 2, (tile + 64) / 2), 3.0, 0.97)
    b = cv2.warpAffine(a, m, (tile + 64, tile + 64), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    cut = slice(32, 32 + tile)
    return (np.clip(a[cut, cut], 0, 65535).astype(np.uint16), np.clip(b[cut, cut], 0, 65535).astype(np.uint16))


def _write_tif(path: Path, arr, **tags) -> None:
    import warnings

    import rasterio
    from rasterio.errors import NotGeoreferencedWarning

    warnings.simplefilter("ignore", NotGeoreferencedWarning)      # the tile is not georeferenced
    with rasterio.open(path, "w", driver="GTiff", width=arr.shape[1], height=arr.shape[0], count=1,
                       dtype=arr.dtype, tiled=True, blockxsize=256, blockysize=256, compress="deflate") as ds:
        ds.write(arr[None])
        if tags:
            ds.update_tags(**tags)


def build_products(root: Path, size: int, tile: int, src: Path | None) -> tuple[Path, Path]:
    """Products A (DIMAP folder of linked tiles) and B (one VRT), see the module docstring."""
    if size % tile:
        raise SystemExit(f"--size {size} is not a multiple of --tile {tile}")
    n = size // tile
    prod = root / "products"
    a_dir, b_vrt = prod / "A", prod / "B" / "IMG_B_BIG.vrt"
    stamp = prod / f".built_{size}_{tile}_{src.name if src else 'demo'}"
    if stamp.exists():
        return a_dir, b_vrt
    import shutil

    shutil.rmtree(prod, ignore_errors=True)
    a_dir.mkdir(parents=True)
    b_vrt.parent.mkdir(parents=True)
    ta, tb = _texture(src, tile)
    _write_tif(prod / "tile_a.tif", ta)
    _write_tif(prod / "tile_b.tif", tb)
    for r in range(1, n + 1):
        for c in range(1, n + 1):
            os.symlink(prod / "tile_a.tif", a_dir / f"IMG_{STEM_A}_R{r}C{c}.TIF")
    (a_dir / f"DIM_{STEM_A}.XML").write_text(DIMAP)
    src_b = (prod / "tile_b.tif").resolve()
    out = [f'<VRTDataset rasterXSize="{size}" rasterYSize="{size}">',
           '  <SRS>EPSG:32740</SRS>',                      # UTM 40S (La Reunion), 0.5 m pixels
           '  <GeoTransform>330000.0, 0.5, 0.0, 7660000.0, 0.0, -0.5</GeoTransform>',
           '  <Metadata><MDI key="TIFFTAG_DATETIME">2024:03:02 10:41:31</MDI></Metadata>',
           '  <VRTRasterBand dataType="UInt16" band="1">']
    for r in range(n):
        for c in range(n):
            out += ['    <SimpleSource>', f'      <SourceFilename relativeToVRT="0">{src_b}</SourceFilename>',
                    '      <SourceBand>1</SourceBand>',
                    f'      <SrcRect xOff="0" yOff="0" xSize="{tile}" ySize="{tile}"/>',
                    f'      <DstRect xOff="{c * tile}" yOff="{r * tile}" xSize="{tile}" ySize="{tile}"/>',
                    '    </SimpleSource>']
    out += ['  </VRTRasterBand>', '</VRTDataset>']
    b_vrt.write_text("\n".join(out) + "\n")
    stamp.write_text("")
    return a_dir, b_vrt


def disk_bytes(folder: Path) -> int:
    return sum(p.lstat().st_size for p in folder.rglob("*"))


# -- the steps, each run in a child process --------------------------------------------------
def run_step(argv: list[str], log: Path) -> tuple[int, float, float, str]:
    """(exit code, wall s, peak RSS MB of the child and its own children, stdout)."""
    t0 = time.time()
    with open(log, "w") as out:
        p = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, cwd=REPO,
                             env={**os.environ, "PYTHONPATH": str(REPO)})
        _, status, ru = os.wait4(p.pid, 0)
        p.returncode = os.waitstatus_to_exitcode(status)
    return p.returncode, time.time() - t0, ru.ru_maxrss / 1024.0, log.read_text()


def child_features(site: str, rows: int, out_json: str) -> None:
    """The sparse stage's feature extraction (stage._features_and_matches up to matching) on the
    top `rows` block rows of each image of the site's first date group."""
    from concurrent.futures import ThreadPoolExecutor
    from dataclasses import replace

    from recon_core.config import Config
    from recon_core.io.site import load_site
    from recon_core.model.grouping import group_by_date
    from recon_core.sparse.features import detect_image, group_tone_curves
    from recon_core.sparse.stage import FEATURE_THREADS

    cfg = Config()
    s = load_site(site)
    group = group_by_date(s.images, cfg.grouping.max_gap_days, cfg.grouping.max_span_days)[0]
    res = {"images": [im.name for im in group.images], "size": [group.images[0].width, group.images[0].height]}
    t0 = time.time()
    tones, _ = group_tone_curves(group.images, cfg.features.stretch_percentiles)
    res["tone_s"], res["tone_hwm_mb"] = time.time() - t0, vm_hwm_mb()
    height = min(group.images[0].height, rows * cfg.features.detect_block)
    strips = [replace(im, height=min(im.height, height)) for im in group.images]
    t0 = time.time()
    with tempfile.TemporaryDirectory(prefix=".sparse_desc_") as folder:
        with ThreadPoolExecutor(max_workers=max(1, min(FEATURE_THREADS, len(strips)))) as ex:
            feats = list(ex.map(lambda k: detect_image(strips[k], cfg.features, tones[k],
                                                       spill=Path(folder) / f"{k}.desc"), range(len(strips))))
        res["spill_bytes"] = sum(f.stat().st_size for f in Path(folder).iterdir())
    res["detect_s"] = time.time() - t0
    res["strip"] = [strips[0].width, height]
    res["keypoints"] = [len(f) for f in feats]
    res["hwm_mb"] = vm_hwm_mb()
    Path(out_json).write_text(json.dumps(res))


def child_overview(site: str, out_json: str) -> None:
    """The coarse overview features of the sparse stage (detect_overview at its factor)."""
    from recon_core.config import Config
    from recon_core.io.site import load_site
    from recon_core.model.grouping import group_by_date
    from recon_core.sparse.features import detect_overview, group_tone_curves

    cfg = Config()
    s = load_site(site)
    group = group_by_date(s.images, cfg.grouping.max_gap_days, cfg.grouping.max_span_days)[0]
    tones, _ = group_tone_curves(group.images, cfg.features.stretch_percentiles)
    factor = cfg.matching.coarse_factor
    n = [len(detect_overview(im, max(1, min(factor, min(im.width, im.height) // 128)), tones[k])[0])
         for k, im in enumerate(group.images)]
    Path(out_json).write_text(json.dumps({"keypoints": n, "hwm_mb": vm_hwm_mb()}))


# -- the parent ------------------------------------------------------------------------------
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", type=Path, default=Path(tempfile.gettempdir()) / "aerec_bench" / "big")
    ap.add_argument("--size", type=int, default=40000, help="product side, px")
    ap.add_argument("--tile", type=int, default=2000, help="the repeated tile's side, px")
    ap.add_argument("--tile-from", type=Path, default=None, help="image whose texture fills the tile")
    ap.add_argument("--rows", default="1,2", help="block rows of features per run, comma-separated")
    ap.add_argument("--budget-gib", type=float, default=2.0, help="peak memory budget per step")
    ap.add_argument("--skip-overview", action="store_true")
    ap.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        kind, *rest = a.child
        if kind == "features":
            child_features(rest[0], int(rest[1]), rest[2])
        else:
            child_overview(rest[0], rest[1])
        return 0

    import shutil

    py = sys.executable
    budget = a.budget_gib * 1024
    a.root.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    prod_a, prod_b = build_products(a.root, a.size, a.tile, a.tile_from)
    print(f"products: 2 x {a.size:,} x {a.size:,} px uint16 ({2 * a.size ** 2 * 2 / 1e9:.1f} GB of pixels), "
          f"{disk_bytes(a.root / 'products') / 1e6:.1f} MB on disk (one {a.tile} px tile each; "
          f"A: {(a.size // a.tile) ** 2} linked DIMAP tiles, B: one VRT), built in {time.time() - t0:.1f} s")
    site = a.root / "site"
    shutil.rmtree(site, ignore_errors=True)
    rows_list = [int(r) for r in a.rows.split(",") if r.strip()]
    ok = True

    def verdict(name, code, wall, peak, extra=""):
        nonlocal ok
        good = code == 0 and peak < budget
        ok &= good
        print(f"{'PASS' if good else 'FAIL'}  {name:44s} {wall:8.1f} s  peak {peak:7.0f} MB"
              f" (budget {budget:.0f} MB){'' if code == 0 else f'  exit {code}'}{extra}")

    code, wall, peak, out = run_step([py, "-m", "recon_core.cli", "site", "init", str(site), str(prod_a),
                                      str(prod_b)], a.root / "site_init.log")
    verdict("aerec site init", code, wall, peak, f"  site {disk_bytes(site) / 1e3:.0f} kB")
    if code:
        print(out)
        return 1
    code, wall, peak, out = run_step([py, "-m", "recon_core.cli", "info", str(site)], a.root / "info.log")
    verdict("aerec info (with the tone curves)", code, wall, peak)
    print("    " + "\n    ".join(out.strip().splitlines()))
    fits = []
    for rows in rows_list:
        res_json = a.root / f"features_{rows}.json"
        code, wall, peak, out = run_step([py, __file__, "--child", "features", str(site), str(rows),
                                          str(res_json)], a.root / f"features_{rows}.log")
        if code:
            verdict(f"features, {rows} block row(s)", code, wall, peak)
            print(out[-3000:])
            continue
        r = json.loads(res_json.read_text())
        kp = sum(r["keypoints"])
        verdict(f"features, top {r['strip'][1]:,} rows x {r['strip'][0]:,} cols", code, wall, peak,
                f"\n      tone curves {r['tone_s']:.1f} s (peak so far {r['tone_hwm_mb']:.0f} MB); SIFT "
                f"{r['detect_s']:.1f} s, {r['keypoints']} keypoints "
                f"({kp / (2 * r['strip'][0] * r['strip'][1] / 1e6):,.0f} per Mpx), "
                f"descriptors spilled {r['spill_bytes'] / 1e6:.0f} MB")
        fits.append((kp, peak, r["strip"][0] * r["strip"][1]))
    if len(fits) >= 2:
        (k1, p1, _), (k2, p2, _) = fits[0], fits[-1]
        per_kp = (p2 - p1) * 2 ** 20 / max(k2 - k1, 1)
        k_full = k2 * a.size ** 2 / fits[-1][2]
        full = p2 + (k_full - k2) * per_kp / 2 ** 20
        good = full < budget
        ok &= good
        print(f"{'PASS' if good else 'FAIL'}  features, whole images (extrapolated)      "
              f"peak grows {per_kp:.0f} B per keypoint: {k_full / 1e6:.1f} M keypoints -> {full:7.0f} MB "
              f"(budget {budget:.0f} MB)")
    if not a.skip_overview:
        res_json = a.root / "overview.json"
        code, wall, peak, out = run_step([py, __file__, "--child", "overview", str(site), str(res_json)],
                                         a.root / "overview.log")
        extra = f"  {json.loads(res_json.read_text())['keypoints']} keypoints" if code == 0 else "\n" + out[-3000:]
        verdict("coarse overview features (detect_overview)", code, wall, peak, extra)
    print("ALL PASS" if ok else "SOME FAIL")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
