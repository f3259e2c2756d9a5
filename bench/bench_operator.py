"""An operator places 4 GCPs in every image of a 3-image site through the browser, as a person
would, and the bench counts the inputs (clicks, keys, wheel notches) and scores each observation
against the truth.

The "person" is headless Chromium driven by Playwright. It never calls into the viewer's Python:
it sees the page (screenshots), presses keys and clicks the mouse, and reads only the files a user
can read (OUT/gcps.geojson, to know that an edit was saved). It knows what each GCP looks like
(a chip of the image around its true pixel, as an operator knows the spot from the survey's
photo) and finds it on the screen by normalised cross-correlation over scales; it aims at the
true sub-pixel position inside what it found. The workflow: N (next GCP), a click on it in the
image on the screen (the loupe opens), a click in the loupe; the viewer then opens the GCP's
next image in the loupe at its prediction, where the person clicks again, and so on; when the
spot is not in the loupe (its best match there is poor), Escape and a click on the whole image.
So the bench measures what the viewer adds: how many inputs it takes, how precisely a click on
the screen becomes a pixel, and how often the predictions bring the spot into the loupe.

    python bench/bench_operator.py                   # generates a 3-image site (2000 px) once
    python bench/bench_operator.py --shots /tmp/op   # also saves a screenshot after each step
    python bench/bench_operator.py --no-survey       # ground positions from an orthoimage + DEM
    python bench/bench_operator.py --no-survey --roof-dem 5   # roof corners, a 5 m DEM
    python bench/bench_operator.py --wrong-clicks    # N with the loupe open; two tabs

--no-survey: the operator has no survey. The working set starts empty; the viewer is given a
reference orthoimage of the site (the generator's true orthoimage, render_ortho, 0.5 m) and a
DEM (the site's truth DSM, as a lidar DEM would be). For each GCP the person presses G (a new
GCP on the orthoimage), finds the spot on the orthoimage as on the images (a chip of the
orthoimage around the GCP's true ground position), clicks it and then clicks it in the loupe:
the GCP gets its ground position from there, and the viewer goes back to the image shown
before, where the person places it as above. Scored: the ground positions against the truth
(horizontal, m; the height is the DEM's at the clicked spot), and the observations as above.

--roof-dem CELL (with --no-survey): the DEM is the truth DSM averaged to CELL metres (a national
DEM, a free global one), and --roofs of the 4 spots (2 by default) are roof corners (textured,
on a roof, within 2 m of its edge), the others flat open ground, as a user picks them: on a
roof, the DEM's height is between the roof's and the ground's. The bench prints, for each GCP, the DEM's height against the truth and
whether the viewer flagged it (sigma_h_m in OUT/gcps.geojson) before any upgrade; then the
height the upgrade's images give each flagged GCP (the function behind "Take the images'
height", called on the working set the person saved, with the site's viewing angles). Target
(the operator issue): every roof-corner GCP within 0.5 m in height, or flagged before the
upgrade.

--wrong-clicks: instead of the session, the two ways a click once saved a wrong observation
(the operator issue): N pressed with the loupe open, then a click at the previous GCP's spot;
and a second browser tab's ordinary click on its image while the first tab's loupe is open. Every
observation added or moved must be within 0.3 px of its GCP's truth, and the first tab's GCP must
stay where it was put.

Site: a synthetic scene (seed 0, one date group of 3 images of 2000 x 2000 px, d = 1000); its
working GCP set holds 4 control GCPs with ground coordinates only (no observation: the operator
has survey coordinates, not pixels). The sparse reconstruction is run first (`aerec run
--stage sparse`), then `aerec view OUT` is opened at 1600 x 1000.

Targets (the operator issue): at most 25 inputs in all, every observation within 0.3 px of the
truth.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

VIEW = {"width": 1600, "height": 1000}
PANEL_PX = 470            # the control panel on the right ("large" control width) is not searched
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader",
         "--disable-quic", "--no-first-run", "--disable-background-networking",
         "--disable-component-update", "--disable-sync"]


# -- the site ---------------------------------------------------------------------------------
def operator_preset():
    from recon_core.synthetic.generator import SynthPreset

    return SynthPreset(name="operator3", groups=(3,), group_months=(5,), image_size=(2000, 2000), n_gcps=12)


def ensure_site(root: Path, seed: int) -> Path:
    from recon_core.synthetic.generator import generate_site

    site = root / f"operator3_s{seed}"
    if not (site / "site.json").exists():
        t0 = time.time()
        generate_site(site, preset=operator_preset(), seed=seed)
        print(f"generated the 3-image site in {time.time() - t0:.0f} s -> {site}")
    return site


def choose_gcps(site: Path, n: int = 4, flat: Path | None = None) -> list[dict]:
    """The site's control GCPs seen in every image (truth file), completed by check points seen
    in every image if fewer than n; `flat` (the reference orthoimage): spots chosen on it where
    the ground is flat (as a user without a survey is told to: a DEM's height at a wall or an
    edge is uncertain), flat_spots."""
    truth = json.loads((site / "truth" / "gcps_truth.json").read_text())["gcps"]
    names = sorted(p.name for p in (site / "images").glob("*.tif"))
    seen = [g for g in truth if set(g["true_observations"]) >= set(names)]
    if flat is not None:
        return flat_spots(site, flat, names, n)
    seen.sort(key=lambda g: g["role"] != "control")
    if len(seen) < n:
        raise SystemExit(f"only {len(seen)} GCPs are seen in all {len(names)} images")
    return seen[:n]


def flat_spots(site: Path, ortho: Path, names: list[str], n: int) -> list[dict]:
    """n spots a user without a survey would choose on the orthoimage: flat ground (the truth
    DSM within 0.3 m over 1 m around), textured (corners of road markings, kerbs), seen in every
    image, one near the centre of each quarter of the site; their true pixels by the images'
    RPCs (the generator's cameras to 0.01 px), their height the truth DSM's."""
    import cv2
    import rasterio

    with rasterio.open(site / "gt_dsm.tif") as ds:
        dsm, tf, crs, nd = ds.read(1).astype(np.float64), ds.transform, ds.crs, ds.nodata
    with rasterio.open(ortho) as ds:
        img = ds.read(1).astype(np.float32)
    ok = dsm != nd
    k = np.ones((5, 5), np.uint8)                                  # 5 x 5 cells = 2 m
    hi = cv2.dilate(np.where(ok, dsm, -1e9).astype(np.float32), k)
    lo = cv2.erode(np.where(ok, dsm, 1e9).astype(np.float32), k)
    corner = cv2.cornerMinEigenVal(img / max(img.max(), 1.0), 5)
    good = ok & (hi - lo < 0.3) & (corner > np.percentile(corner[ok], 90))
    rows, cols, llh, pix, inside = _seen_cells(site, names, good, dsm, tf, crs)
    H, W = dsm.shape
    out = []
    for qr, qc in ((0.25, 0.25), (0.25, 0.75), (0.75, 0.75), (0.75, 0.25)):
        d = np.hypot(rows - qr * H, cols - qc * W) + np.where(inside, 0, 1e9)
        i = int(np.argmin(d))
        out.append({"id": f"FLAT-{len(out) + 1}", "role": "control", "llh": [float(v) for v in llh[i]],
                    "true_observations": {nm: [float(v) for v in pix[nm][i]] for nm in names}})
    return out[:n]


def roof_spots(site: Path, ortho: Path, dem: Path, names: list[str], n: int, roofs: int = 2) -> list[dict]:
    """n spots a user would click on the orthoimage, `roofs` of them roof corners (the truth DSM 2 m
    or more above the DEM there: the DEM smooths the building into the ground around it, within
    2 m of its edge) and flat open ground (the truth within 0.3 m over 5 m around, as a user
    told to prefer open ground picks it; the DEM within 0.3 m of it), textured, seen in every
    image, one near the centre of each quarter of the site;
    their true pixels by the images' RPCs, their height the truth DSM's."""
    import cv2
    import rasterio
    from pyproj import Transformer

    from recon_core.bend.dem import open_reference_dem

    with rasterio.open(site / "gt_dsm.tif") as ds:
        dsm, tf, crs, nd = ds.read(1).astype(np.float64), ds.transform, ds.crs, ds.nodata
    with rasterio.open(ortho) as ds:
        img = ds.read(1).astype(np.float32)
    ok = dsm != nd
    rows, cols = np.nonzero(ok)
    e, nn = tf.c + (cols + 0.5) * tf.a, tf.f + (rows + 0.5) * tf.e
    lon, lat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(e, nn)
    above = np.full(dsm.shape, -1e9)
    above[rows, cols] = dsm[rows, cols] - open_reference_dem(dem).heights(np.asarray(lon), np.asarray(lat))
    k = int(max(1, round(2.0 / abs(tf.a))))                      # 2 m in cells
    k_open = int(max(1, round(5.0 / abs(tf.a))))                 # 5 m: open ground
    lo = cv2.erode(np.where(ok, dsm, 1e9).astype(np.float32), np.ones((2 * k + 1, 2 * k + 1), np.uint8))
    corner = cv2.cornerMinEigenVal(img / max(img.max(), 1.0), 5)
    textured = corner > np.percentile(corner[ok], 80)
    roof = ok & (above > 2.0) & (dsm - lo > 2.0) & textured
    box = np.ones((2 * k_open + 1, 2 * k_open + 1), np.uint8)
    open_range = (cv2.dilate(np.where(ok, dsm, -1e9).astype(np.float32), box)
                  - cv2.erode(np.where(ok, dsm, 1e9).astype(np.float32), box))
    flat = ok & (np.abs(above) < 0.3) & (open_range < 0.3) & textured
    kind = np.where(roof, 1, np.where(flat, 2, 0))
    good = kind > 0
    rows, cols, llh, pix, inside = _seen_cells(site, names, good, dsm, tf, crs)
    H, W = dsm.shape
    out = []
    kinds = kind[rows, cols]
    for q, (qr, qc) in enumerate(((0.25, 0.25), (0.25, 0.75), (0.75, 0.75), (0.75, 0.25))):
        want = 1 if q in (0, 2, 1, 3)[:roofs] else 2
        d = np.hypot(rows - qr * H, cols - qc * W) + np.where(inside & (kinds == want), 0, 1e9)
        i = int(np.argmin(d))
        out.append({"id": f"{'ROOF' if want == 1 else 'FLAT'}-{len(out) + 1}", "role": "control",
                    "llh": [float(v) for v in llh[i]],
                    "true_observations": {nm: [float(v) for v in pix[nm][i]] for nm in names}})
    return out[:n]


def coarse_dem(site: Path, dst: Path, cell_m: float) -> Path:
    """The truth DSM averaged to cell_m metres (a coarse DEM: buildings smoothed into the ground)."""
    import rasterio
    from affine import Affine
    from rasterio.enums import Resampling

    with rasterio.open(site / "gt_dsm.tif") as ds:
        f = max(1, int(round(cell_m / abs(ds.transform.a))))
        h, w = ds.height // f, ds.width // f
        a = ds.read(1, out_shape=(h, w), resampling=Resampling.average, masked=True).astype(np.float32)
        prof = ds.profile | {"width": w, "height": h, "dtype": "float32", "nodata": -9999.0,
                             "transform": ds.transform * Affine.scale(ds.width / w, ds.height / h)}
    with rasterio.open(dst, "w", **prof) as out:
        out.write(np.ma.filled(a, -9999.0)[None])
    return dst


def images_heights(site: Path, out: Path) -> dict[str, tuple[float, float | None]]:
    """GCP id -> (its height in the working set, the height the upgrade's images give it), for
    the GCPs flagged as doubtful: the Upgrade button's fit and "Take the images' height"'s
    reading of it, on the working set as saved."""
    from dataclasses import fields

    from aerec_viewer.results import UpgradeOutcome, images_height
    from recon_core.config import Config
    from recon_core.euclidean.upgrade_stage import upgrade_models
    from recon_core.io.gcps import read_gcps_geojson
    from recon_core.io.layout import OutLayout
    from recon_core.io.models import load_model
    from recon_core.io.site import load_site

    st = load_site(site)
    gcps = read_gcps_geojson(out / "gcps.geojson")
    models = {g: load_model(out, g) for g in OutLayout(out).model_groups()}
    up = upgrade_models(gcps, models, Config(), {im.name: im for im in st.images})
    outcome = UpgradeOutcome(**{f.name: getattr(up, f.name) for f in fields(up)}, gcps_version=0, gcps_key="")
    return {g.id: (g.h, images_height(outcome, g)) for g in gcps if g.sigma_h_m is not None}


def _seen_cells(site: Path, names: list[str], good: np.ndarray, dsm: np.ndarray, tf, crs):
    """The truth DSM's cells `good` as candidate spots: (rows, cols, their lon, lat, h, their
    true pixels per image by the images' RPCs, seen 100 px or more inside every image)."""
    import rasterio
    from pyproj import Transformer

    from recon_core.geometry.rpc import RPCModel

    rows, cols = np.nonzero(good)
    e, nn = tf.c + (cols + 0.5) * tf.a, tf.f + (rows + 0.5) * tf.e
    lon, lat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(e, nn)
    llh = np.column_stack([lon, lat, dsm[rows, cols]])
    inside = np.ones(len(llh), bool)
    pix = {}
    for name in names:
        with rasterio.open(site / "images" / name) as ds:
            rpc, w, h = RPCModel.from_rasterio(ds.rpcs), ds.width, ds.height
        p = rpc.project(llh)
        pix[name] = p
        inside &= (p[:, 0] > 100) & (p[:, 0] < w - 100) & (p[:, 1] > 100) & (p[:, 1] < h - 100)
    return rows, cols, llh, pix, inside


def prepare_out(site: Path, out: Path, gcps: list[dict]) -> None:
    """Sparse reconstruction, then the working set = the chosen GCPs, ground coordinates only
    (none at all without a survey: `gcps` empty)."""
    from recon_core.io.gcps import GCP, write_gcps_geojson

    if not (out / "report.json").exists():
        t0 = time.time()
        subprocess.run(["aerec", "run", str(site), "--out", str(out), "--stage", "sparse", "--quiet"],
                       check=True)
        print(f"sparse reconstruction in {time.time() - t0:.0f} s -> {out}")
    write_gcps_geojson(out / "gcps.geojson",
                       [GCP(g["id"], *g["llh"], role="control") for g in gcps],
                       written_by="bench_operator (ground coordinates only)")


def prepare_reference(site: Path, root: Path, seed: int, roof_dem_m: float | None = None) -> tuple[Path, Path]:
    """The reference orthoimage (the generator's true one) and DEM (the truth DSM, or it averaged
    to roof_dem_m metres) of the site."""
    from recon_core.synthetic.generator import render_ortho

    ref = root / f"operator3_s{seed}_reference"
    ortho, dem = ref / "ortho.tif", ref / "dem.tif"
    if not ortho.exists():
        ref.mkdir(parents=True, exist_ok=True)
        render_ortho(site, ortho, operator_preset(), seed)
        shutil.copy(site / "gt_dsm.tif", dem)
    if roof_dem_m:
        coarse = ref / f"dem_{roof_dem_m:g}m.tif"
        if not coarse.exists():
            coarse_dem(site, coarse, roof_dem_m)
        return ortho, coarse
    return ortho, dem


def read_ground(out: Path) -> dict[str, tuple[float, float, float]]:
    """Each GCP's (lon, lat, h) in the working set."""
    try:
        doc = json.loads((out / "gcps.geojson").read_text())
    except (OSError, ValueError):
        return {}
    return {f["properties"]["id"]: tuple(f["geometry"]["coordinates"]) for f in doc["features"]}


# -- the person -------------------------------------------------------------------------------
class Person:
    """Sees screenshots, clicks and presses keys; counts every input."""

    def __init__(self, page, shots: Path | None):
        self.page = page
        self.inputs: list[str] = []
        self.shots = shots
        self._k = 0

    def screen(self) -> np.ndarray:
        import cv2

        png = self.page.screenshot()
        return cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_GRAYSCALE)

    def settle(self, timeout: float = 20.0) -> np.ndarray:
        """Wait until the screen stops changing (camera transitions, textures arriving)."""
        t0, last = time.time(), self.screen()
        while time.time() - t0 < timeout:
            time.sleep(0.4)
            now = self.screen()
            if np.abs(now.astype(np.int16) - last).max() <= 2:
                return now
            last = now
        return last

    def shot(self, name: str) -> None:
        if self.shots is not None:
            self._k += 1
            self.page.screenshot(path=str(self.shots / f"{self._k:02d}_{name}.png"))

    def click(self, x: float, y: float, what: str) -> None:
        self.inputs.append(f"click {what}")
        self.page.mouse.click(x, y)

    def key(self, k: str, what: str) -> None:
        self.inputs.append(f"key {k} ({what})")
        self.page.keyboard.press(k)

    def click_role(self, role: str, name: str) -> None:
        self.inputs.append(f"click {role} '{name}'")
        self.page.get_by_role(role, name=name).first.click()


def chip(img: np.ndarray, col: float, row: float, half: int) -> tuple[np.ndarray, int, int]:
    c0, r0 = int(round(col)) - half, int(round(row)) - half
    c0 = min(max(c0, 0), img.shape[1] - 2 * half - 1)
    r0 = min(max(r0, 0), img.shape[0] - 2 * half - 1)
    return img[r0:r0 + 2 * half + 1, c0:c0 + 2 * half + 1].astype(np.float32), c0, r0


def find_on_screen(screen: np.ndarray, img: np.ndarray, col: float, row: float, *, half: int,
                   scales: np.ndarray, nearest: bool) -> tuple[float, float, float, float]:
    """Where the true pixel (col, row) of `img` is on the screen: the chip around it matched over
    scales (screen px per image px); returns (x, y, scale, ncc)."""
    import cv2

    c, c0, r0 = chip(img, col, row, half)
    c = (c - c.mean()) / (c.std() + 1e-6)
    region = screen[:, : screen.shape[1] - PANEL_PX].astype(np.float32)
    best = (-2.0, 0.0, 0.0, 1.0)
    for s in scales:
        w = int(round(c.shape[1] * s))
        h = int(round(c.shape[0] * s))
        if w < 10 or h < 10 or w >= region.shape[1] or h >= region.shape[0]:
            continue
        t = cv2.resize(c, (w, h), interpolation=cv2.INTER_NEAREST if nearest else cv2.INTER_AREA)
        res = cv2.matchTemplate(region, t, cv2.TM_CCOEFF_NORMED)
        _, v, _, loc = cv2.minMaxLoc(res)
        if v > best[0]:
            best = (v, loc[0], loc[1], w / c.shape[1], h / c.shape[0])
    v, x0, y0, sx, sy = best
    return x0 + (col - c0 + 0.5) * sx, y0 + (row - r0 + 0.5) * sy, sx, v


def read_working_set(out: Path) -> dict[str, dict[str, tuple[float, float]]]:
    try:
        doc = json.loads((out / "gcps.geojson").read_text())
    except (OSError, ValueError):
        return {}
    return {f["properties"]["id"]: {k: tuple(v) for k, v in f["properties"].get("observations", {}).items()}
            for f in doc["features"]}


def saved_after(out: Path, t: float, timeout: float = 30.0) -> None:
    """Wait until the working set is written after time t (the viewer saves after every edit)."""
    t0 = time.time()
    while time.time() - t0 < timeout:
        try:
            if (out / "gcps.geojson").stat().st_mtime > t:
                return
        except OSError:
            pass
        time.sleep(0.2)


def wait_file(out: Path, cond, timeout: float = 30.0):
    t0 = time.time()
    while time.time() - t0 < timeout:
        obs = read_working_set(out)
        if cond(obs):
            return obs
        time.sleep(0.2)
    return None


def wait_hint(page, left: list[str], timeout: float = 8.0) -> str | None:
    """The image the viewer's note says it shows in the loupe, among `left` (the note the person
    reads in the GCP tab), or None."""
    t0 = time.time()
    while time.time() - t0 < timeout:
        for el in page.locator("text=shown in the loupe >> visible=true").all():
            try:
                txt = el.inner_text(timeout=1_000)
            except Exception:
                continue
            im = next((n for n in left if f"in {n}: predicted" in txt), None)
            if im is not None:
                return im
        time.sleep(0.2)
    return None


def place(person: Person, out: Path, img: np.ndarray, gid: str, image: str, true_xy) -> bool:
    """Click the GCP on the whole image (the loupe opens there), then click it in the loupe."""
    screen = person.settle()
    x, y, s, v = find_on_screen(screen, img, *true_xy, half=48,
                                scales=np.geomspace(0.12, 2.5, 40), nearest=False)
    if v < 0.4:
        print(f"  {gid} in {image}: not found on the screen (NCC {v:.2f})")
        return False
    person.click(x, y, f"{gid} on {image}")
    return click_in_loupe(person, out, img, gid, image, true_xy)


def click_in_loupe(person: Person, out: Path, img: np.ndarray, gid: str, image: str, true_xy) -> bool:
    """The loupe is open: find the spot among the enlarged pixels and click it."""
    person.settle()
    person.shot(f"{gid}_{image}_loupe")
    screen = person.settle()
    x, y, s, v = find_on_screen(screen, img, *true_xy, half=8,
                                scales=np.geomspace(3.0, 40.0, 40), nearest=True)
    if v < 0.8:        # the enlarged pixels are the image's own: the spot matches at ~0.95+
        print(f"  {gid} in {image}: not in the loupe (best NCC {v:.2f})")
        return False
    x, y, s, v = find_on_screen(screen, img, *true_xy, half=8,
                                scales=np.linspace(0.94 * s, 1.06 * s, 25), nearest=True)
    person.click(x, y, f"{gid} in the loupe on {image} ({s:.1f} screen px per image px)")
    return wait_file(out, lambda o: image in o.get(gid, {})) is not None


def place_ground(person: Person, out: Path, ortho: np.ndarray, true_px, label: str) -> str | None:
    """Click the GCP's spot on the reference orthoimage, then in the loupe: a new GCP with that
    ground position appears in the working set; returns its id."""
    before = set(read_ground(out))
    screen = person.settle()
    x, y, s, v = find_on_screen(screen, ortho, *true_px, half=48, scales=np.geomspace(0.12, 2.5, 40),
                                nearest=False)
    if v < 0.4:
        print(f"  {label} on the orthoimage: not found on the screen (NCC {v:.2f})")
        return None
    person.click(x, y, f"{label} on the orthoimage")
    person.settle()
    screen = person.settle()
    x, y, s, v = find_on_screen(screen, ortho, *true_px, half=8, scales=np.geomspace(3.0, 40.0, 40), nearest=True)
    if v < 0.8:
        print(f"  {label}: not in the orthoimage's loupe (best NCC {v:.2f})")
        return None
    x, y, s, v = find_on_screen(screen, ortho, *true_px, half=8, scales=np.linspace(0.94 * s, 1.06 * s, 25),
                                nearest=True)
    person.click(x, y, f"{label} in the loupe on the orthoimage ({s:.1f} screen px per px)")
    got = wait_file(out, lambda o: set(o) - before)
    return None if got is None else sorted(set(got) - before)[0]


# -- the wrong clicks of the operator issue -----------------------------------------------------
def wrong_observations(before: dict, after: dict, gcps: list[dict], tol: float = 0.3) -> list[str]:
    """Observations added or moved between two readings of the working set that are not within
    tol px of their GCP's truth (a click recorded for a GCP at another's spot)."""
    truth = {g["id"]: g["true_observations"] for g in gcps}
    bad = []
    for gid, obs in after.items():
        for im, xy in obs.items():
            if before.get(gid, {}).get(im) == xy:
                continue
            t = truth.get(gid, {}).get(im)
            e = None if t is None else float(np.hypot(xy[0] - t[0], xy[1] - t[1]))
            if e is None or e > tol:
                bad.append(f"{gid} in {im} at ({xy[0]:.2f}, {xy[1]:.2f}), "
                           + ("no truth" if e is None else f"{e:.2f} px from its spot"))
    for gid, obs in before.items():
        for im in obs:
            if im not in after.get(gid, {}):
                bad.append(f"{gid} in {im}: removed")
    return bad


def open_gcp_tab(page, person: "Person") -> None:
    page.get_by_role("tab", name="GCPs").wait_for(timeout=60_000)
    person.click_role("tab", "GCPs")
    person.key("l", "look at the image plane")


def on_the_plane(screen: np.ndarray, images: dict[str, np.ndarray], g: dict):
    """(image, find_on_screen's answer) for the image on the screen where the GCP's spot matches
    best: the person does not know which image the plane shows."""
    return max(((n, find_on_screen(screen, images[n], *g["true_observations"][n], half=48,
                                   scales=np.geomspace(0.12, 2.5, 40), nearest=False))
                for n in images), key=lambda t: t[1][3])


def wrong_clicks(browser, url: str, out: Path, gcps: list[dict], names: list[str],
                 images: dict[str, np.ndarray], shots: Path | None) -> bool:
    """The two ways a click once saved a wrong observation (the operator issue), as a person does
    them; True when nothing wrong was recorded.

    N with the loupe open: the person clicks GCP A on the image (the loupe opens), presses N,
    and clicks A's spot in the loupe with the new GCP B selected. Two tabs: tab 1 places A, then
    clicks it again (its loupe opens); a second person in another browser tab sees the GCP tab
    and clicks B's spot on the image on their screen."""
    a, b = gcps[0], gcps[1]
    im = names[0]
    page = browser.new_context(viewport=VIEW).new_page()
    page.goto(url)
    p1 = Person(page, shots)
    open_gcp_tab(page, p1)
    page.get_by_text(f"{a['id']} (control)").first.wait_for(timeout=20_000)
    ok = True
    # -- N with the loupe open
    screen = p1.settle()
    x, y, _, v = find_on_screen(screen, images[im], *a["true_observations"][im], half=48,
                                scales=np.geomspace(0.12, 2.5, 40), nearest=False)
    if v < 0.4:
        print(f"  {a['id']} not found on the screen (NCC {v:.2f}): the run says nothing")
        return False
    p1.click(x, y, f"{a['id']} on {im} (the loupe opens)")
    p1.settle()
    before = read_working_set(out)
    p1.key("n", f"next GCP ({b['id']}) with the loupe open")
    page.get_by_text(f"{b['id']} (control)").first.wait_for(timeout=20_000)
    screen = p1.settle()
    x, y, s, v = find_on_screen(screen, images[im], *a["true_observations"][im], half=8,
                                scales=np.geomspace(3.0, 40.0, 40), nearest=True)
    where = "in a loupe still open" if v >= 0.8 else "on the image (the loupe was closed)"
    if v < 0.8:
        x, y, s, v = find_on_screen(screen, images[im], *a["true_observations"][im], half=48,
                                    scales=np.geomspace(0.12, 2.5, 40), nearest=False)
    p1.click(x, y, f"{a['id']}'s spot {where}, {b['id']} selected")
    time.sleep(3.0)
    bad = wrong_observations(before, read_working_set(out), gcps)
    print(f"N with the loupe open: the click landed {where}; "
          + ("nothing wrong recorded [ok]" if not bad else f"WRONG: {'; '.join(bad)} [FAIL]"))
    ok &= not bad
    p1.key("Escape", "leave the loupe")
    # -- two tabs
    p1.key("p", f"back to {a['id']}")
    page.get_by_text(f"{a['id']} (control)").first.wait_for(timeout=20_000)
    if not place(p1, out, images[im], a["id"], im, a["true_observations"][im]):
        print(f"  {a['id']} could not be placed in tab 1: the two-tab run says nothing")
        return False
    p1.key("Escape", "leave the loupe (the viewer walked on to A's next image)")
    screen = p1.settle()
    # the image on the plane now: where A's spot matches best
    im, (x, y, _, v) = on_the_plane(screen, images, a)
    p1.click(x, y, f"{a['id']} on {im} (NCC {v:.2f}): tab 1's loupe opens")
    p1.settle()
    loupe = page.get_by_role("button", name="Leave the loupe").first.is_enabled()
    before = read_working_set(out)
    page2 = browser.new_context(viewport=VIEW).new_page()
    page2.goto(url)
    p2 = Person(page2, shots)
    open_gcp_tab(page2, p2)
    screen = p2.settle()
    im2, (x, y, s, v) = on_the_plane(screen, images, b)
    p2.click(x, y, f"tab 2: {b['id']}'s spot in {im2} on what its screen shows (NCC {v:.2f}, "
                   f"{s:.2f} px/px)")
    print(f"  tab 1's loupe {'open' if loupe else 'NOT open'} on {im} when tab 2 clicked")
    time.sleep(3.0)
    after = read_working_set(out)
    bad = wrong_observations(before, after, gcps)
    moved = after.get(a["id"], {}) != before.get(a["id"], {})
    print(f"two tabs: tab 2's click while tab 1's loupe is open: "
          + ("nothing wrong recorded" if not bad else f"WRONG: {'; '.join(bad)}")
          + (f", {a['id']} moved [FAIL]" if moved else f", {a['id']} where tab 1 put it")
          + (" [ok]" if not bad and not moved and loupe else " [FAIL]"))
    ok &= not bad and not moved and loupe
    p1.shot("wrong_clicks_tab1")
    p2.shot("wrong_clicks_tab2")
    return ok


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", type=Path, default=Path("/tmp/aerec_bench"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--shots", type=Path, default=None, help="save a screenshot after each step")
    ap.add_argument("--no-survey", action="store_true",
                    help="no ground coordinates: take them from a reference orthoimage + DEM")
    ap.add_argument("--wrong-clicks", action="store_true",
                    help="instead of the session: N with the loupe open, and a second tab's click "
                         "while the first tab's loupe is open (the operator issue's two bugs)")
    ap.add_argument("--roof-dem", type=float, default=None, metavar="CELL",
                    help="with --no-survey: a DEM of CELL metres and GCPs on roof corners")
    ap.add_argument("--roofs", type=int, default=2, choices=range(5),
                    help="with --roof-dem: how many of the 4 GCPs are roof corners")
    args = ap.parse_args()
    if args.roof_dem and not args.no_survey:
        ap.error("--roof-dem goes with --no-survey")

    import rasterio
    from playwright.sync_api import sync_playwright

    site = ensure_site(args.root, args.seed)
    reference = prepare_reference(site, args.root, args.seed, args.roof_dem) if args.no_survey else None
    if args.roof_dem:
        gcps = roof_spots(site, reference[0], reference[1], sorted(p.name for p in (site / "images").glob("*.tif")), 4,
                          args.roofs)
    else:
        gcps = choose_gcps(site, flat=None if reference is None else reference[0])
    out = args.root / f"operator3_s{args.seed}_out"
    prepare_out(site, out, gcps)
    extra: list[str] = []
    if args.no_survey:
        from pyproj import Transformer

        ortho_path, dem_path = reference
        survey = out
        out = args.root / f"operator3_s{args.seed}_nosurvey{f'_roof{args.roofs}' if args.roof_dem else ''}_out"
        if out.exists():
            shutil.rmtree(out)
        shutil.copytree(survey, out, ignore=shutil.ignore_patterns(".aerec.lock"))
        prepare_out(site, out, [])                      # an empty working set
        extra = ["--reference-ortho", str(ortho_path), "--reference-dem", str(dem_path)]
        with rasterio.open(ortho_path) as ds:
            ortho = ds.read(1).astype(np.float32)
            tf, crs = ds.transform, ds.crs
        to_map = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
        for g in gcps:
            e, n = to_map.transform(g["llh"][0], g["llh"][1])
            g["ortho_px"] = ((e - tf.c) / tf.a - 0.5, (n - tf.f) / tf.e - 0.5)
    names = sorted(p.name for p in (site / "images").glob("*.tif"))
    images = {}
    for n in names:
        with rasterio.open(site / "images" / n) as ds:
            images[n] = ds.read(1).astype(np.float32)
    if args.shots:
        args.shots.mkdir(parents=True, exist_ok=True)

    t0 = time.time()
    proc = subprocess.Popen([sys.executable, "-m", "aerec_viewer", str(out), "--port", "0",
                             "--no-browser-hint", *extra], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, env=dict(os.environ))
    lines: list[str] = []
    threading.Thread(target=lambda: lines.extend(iter(proc.stdout.readline, "")), daemon=True).start()
    try:
        while not any(ln.startswith("aerec view: open") for ln in lines):
            if proc.poll() is not None or time.time() - t0 > 120:
                raise SystemExit("the viewer did not start:\n" + "".join(lines[-20:]))
            time.sleep(0.2)
        url = next(ln for ln in lines if ln.startswith("aerec view: open")).split()[-1]
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path="/usr/bin/chromium", args=FLAGS, headless=True)
            if args.wrong_clicks:
                ok = wrong_clicks(browser, url, out, gcps, names, images, args.shots)
                browser.close()
                print("the wrong clicks: " + ("none recorded anything wrong" if ok else "FAIL"))
                return
            page = browser.new_context(viewport=VIEW).new_page()
            page.goto(url)
            page.get_by_role("tab", name="GCPs").wait_for(timeout=60_000)
            person = Person(page, args.shots)
            t_start = time.time()
            person.click_role("tab", "GCPs")
            person.key("l", "look at the image plane")
            person.shot("start")
            shown = 0                                   # index of the image on the plane
            for g in gcps:
                gid = g["id"]
                if args.no_survey:
                    person.key("g", "a new GCP on the reference orthoimage")
                    page.get_by_text("a new GCP: click its spot").first.wait_for(state="attached", timeout=20_000)
                    gid = place_ground(person, out, ortho, g["ortho_px"], g["id"])
                    if gid is None:
                        continue
                    g["viewer_id"] = gid                # the viewer names it; the truth is g's
                else:
                    # the GCP tab opens on the first GCP still to place: N only from there on
                    if not page.get_by_text(f"{gid} (control)").first.is_visible():
                        person.key("n", "next GCP")
                    page.get_by_text(f"{gid} (control)").first.wait_for(timeout=20_000)
                im = names[shown]                       # start in the image on the screen
                if not place(person, out, images[im], gid, im, g["true_observations"][im]):
                    continue
                # "Then its next image": after each click in the loupe the viewer opens the
                # GCP's next image in the loupe at its prediction (its note says "shown in the
                # loupe"); the person clicks the exact pixel there, or, when the GCP is not in
                # the loupe, leaves it (Escape) and clicks it on the whole image
                for _ in range(2 * len(names)):
                    obs = read_working_set(out).get(gid, {})
                    if len(obs) == len(names):
                        break
                    im = wait_hint(page, [n for n in names if n not in obs])
                    if im is None:
                        print(f"  {gid}: images left ({sorted(set(names) - set(obs))}) but no loupe shown")
                        break
                    shown = names.index(im)
                    if click_in_loupe(person, out, images[im], gid, im, g["true_observations"][im]):
                        continue
                    person.key("Escape", "leave the loupe")
                    if not place(person, out, images[im], gid, im, g["true_observations"][im]):
                        break
            t_total = time.time() - t_start
            browser.close()
    finally:
        proc.terminate()
        proc.wait(20)

    obs = read_working_set(out)
    errs, rows = [], []
    if args.no_survey:
        from recon_core.geometry.geodesy import LocalFrame

        ground = read_ground(out)
        print("ground positions from the orthoimage + DEM against the truth:")
        for g in gcps:
            got = ground.get(g.get("viewer_id"))
            if got is None:
                print(f"  {g['id']}: not placed")
                continue
            enu = LocalFrame(*g["llh"]).geodetic_to_enu(np.array([got]))[0]
            print(f"  {g['id']} (as {g['viewer_id']}): horizontal {np.hypot(enu[0], enu[1]):.3f} m, "
                  f"height {enu[2]:+.3f} m")
        if args.roof_dem:
            flagged = images_heights(site, out)
            print("heights: the DEM's, flagged before the upgrade, and the images' after it (m, against the truth):")
            for g in gcps:
                vid = g.get("viewer_id")
                if vid is None or vid not in ground:
                    continue
                dem_err = ground[vid][2] - g["llh"][2]
                got = flagged.get(vid, (None, None))[1]
                verdict = ("flagged" if vid in flagged else "NOT flagged") + (
                    "" if got is None else f"; the images' height {got[0] - g['llh'][2]:+.3f} m"
                    + ("" if got[1] is None else f" (their sigma {got[1]:.2f} m)"))
                ok = vid in flagged or abs(dem_err) <= 0.5
                print(f"  {g['id']}: the DEM's {dem_err:+.3f} m, {verdict}  [{'ok' if ok else 'FAIL'}]")
    for g in gcps:
        for n in names:
            t = g["true_observations"][n]
            o = obs.get(g.get("viewer_id", g["id"]), {}).get(n)
            e = None if o is None else float(np.hypot(o[0] - t[0], o[1] - t[1]))
            errs.append(e)
            rows.append(f"  {g['id']} {n}: " + ("missing" if e is None else f"{e:.3f} px"))
    print(f"\ninputs: {len(person.inputs)} (target <= 25" + (" with a survey; without one, 2 clicks "
          "and G more per GCP)" if args.no_survey else ")"))
    for i in person.inputs:
        print(f"  {i}")
    print("observations against the truth:")
    print("\n".join(rows))
    got = [e for e in errs if e is not None]
    print(f"placed {len(got)} / {len(errs)}; within 0.3 px: {sum(e <= 0.3 for e in got)}; "
          f"max {max(got, default=float('nan')):.3f} px, median {np.median(got) if got else float('nan'):.3f} px")
    print(f"wall time of the session (waiting included): {t_total:.0f} s")


if __name__ == "__main__":
    main()
