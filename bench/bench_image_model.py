"""How well one camera model per image represents a true pushbroom image, against alternatives.

For each image of a synthetic preset (cameras only, no rendering): a 41 x 41 pixel grid localised
at 4 heights spanning the scene, in the scene's local ENU frame; models fitted by least squares
(the rational ones by Levenberg-Marquardt); RMS and max error in pixels over the whole image.

  affine      one 2 x 4 affine camera
  LP          Gupta & Hartley's linear pushbroom (row linear in X, column a ratio of affine)
  LP+row3     LP plus cubic polynomials of the row in both coordinates (attitude drift)
  quadratic   affine plus every quadratic monomial of X (the dome-as-gauge family)
  straight    this project's image model without its focal-plane terms (a straight line array)
  pushbroom   this project's image model (recon_core.bend.image_model)

A site of another simulator whose images carry RPCs fitted to its true cameras (omaha_3dates) is
read with --site: the RPCs stand for the true cameras.

    python bench/bench_image_model.py --preset large
    python bench/bench_image_model.py --site ../shared/data/omaha_3dates
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from recon_core.bend.pushbroom import STRAIGHT_LINE_TERMS, col_basis, row_basis
from recon_core.geometry.geodesy import LocalFrame
from recon_core.synthetic.generator import design_cameras


def grid(cam, frame, heights, n=41):
    g = np.linspace(0.0, 1.0, n)
    gc, gr = np.meshgrid(g * (cam.width - 1), g * (cam.height - 1))
    cr = np.tile(np.stack([gc.ravel(), gr.ravel()], -1), (len(heights), 1))
    h = np.repeat(heights, n * n)
    return frame.geodetic_to_enu(cam.localize(cr, h)), cr


def linear_lsq(B_row, B_col, uv):
    e = [B @ np.linalg.lstsq(B, uv[:, k], rcond=None)[0] - uv[:, k] for k, B in ((0, B_col), (1, B_row))]
    return np.hypot(*e)


def lp_fit(X, uv, drift_degree=0):
    Xh = np.hstack([(X - X.mean(0)) / X.std(0).max(), np.ones((len(X), 1))])
    A = np.linalg.lstsq(Xh, uv, rcond=None)[0]
    r0, rs = uv[:, 1].mean(), uv[:, 1].std()
    nk = max(drift_degree - 1, 0)

    def model(p):
        row = Xh @ p[0:4]
        col = (Xh @ p[4:8]) / (Xh @ np.r_[p[8:11], 1.0])
        t = (row - r0) / rs
        k = p[11:].reshape(2, nk) if nk else np.zeros((2, 0))
        for j in range(nk):
            col = col + k[0, j] * t ** (j + 2)
            row = row + k[1, j] * t ** (j + 2)
        return np.stack([col, row], -1)

    p0 = np.r_[A[:, 1], A[:, 0], 0.0, 0.0, 0.0, np.zeros(2 * nk)]
    p = least_squares(lambda p: (model(p) - uv).ravel(), p0, method="lm", x_scale="jac").x
    return np.linalg.norm(model(p) - uv, axis=1)


class _RPCCamera:
    """An image's RPC standing for its true camera (a simulator's site: omaha_3dates)."""

    def __init__(self, path):
        import rasterio

        from recon_core.geometry.rpc import RPCModel

        with rasterio.open(path) as src:
            self.rpc, self.width, self.height = RPCModel.from_rasterio(src.rpcs), src.width, src.height

    def localize(self, cr, h):
        return self.rpc.localize(cr, h)


def site_cameras(site: Path):
    """(frame, heights, {name: camera}) of a site whose images' RPCs are its true cameras."""
    cams = {p.name: _RPCCamera(p) for p in sorted((site / "images").glob("*.tif"))}
    rpc = next(iter(cams.values())).rpc
    frame = LocalFrame(rpc.long_off, rpc.lat_off, rpc.height_off)
    return frame, np.linspace(rpc.height_off - 0.4 * rpc.height_scale, rpc.height_off + 0.4 * rpc.height_scale, 4), cams


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--preset", default="large")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--site", type=Path, default=None, help="a site whose images' RPCs are its true cameras")
    a = ap.parse_args(argv)
    if a.site:
        frame, heights, cams = site_cameras(a.site)
        print(f"{a.site.name} (the RPCs as true cameras): RMS / max error over each whole image (px)")
    else:
        scene, cams = design_cameras(a.preset, a.seed)
        frame = LocalFrame(scene.lon0, scene.lat0, scene.h0)
        heights = np.linspace(*scene.height_bounds(), 4)
        print(f"{a.preset} seed {a.seed}: RMS / max error over each whole image (px)")
    cols = ("affine", "LP", "LP+row3", "quadratic", "straight", "pushbroom")
    print(f"{'image':<12}{'size':>11}  " + "".join(f"{c:>13}" for c in cols))
    nr, nc = STRAIGHT_LINE_TERMS
    for name, cam in cams.items():
        X, uv = grid(cam, frame, heights)
        one = np.ones((len(X), 1))
        Xh = np.hstack([X, one])
        mean_cam = np.linalg.lstsq(Xh, uv, rcond=None)[0].T
        p = Xh @ mean_cam.T
        p0, ps = p.mean(0), float(np.sqrt(((p - p.mean(0)) ** 2).sum(1).mean()))
        r, c = (p[:, 1] - p0[1]) / ps, (p[:, 0] - p0[0]) / ps
        Xn = (X - X.mean(0)) / float(np.sqrt(((X - X.mean(0)) ** 2).sum(1).mean()))
        quad = np.stack([Xn[:, i] * Xn[:, j] for i in range(3) for j in range(i, 3)], -1)
        Br, Bc = row_basis(Xn, r, c), col_basis(Xn, r, c)
        errs = {"affine": linear_lsq(Xh, Xh, uv), "LP": lp_fit(X, uv), "LP+row3": lp_fit(X, uv, 3),
                "quadratic": linear_lsq(np.hstack([Xh, quad]), np.hstack([Xh, quad]), uv),
                "straight": linear_lsq(Br[:, :nr], Bc[:, :nc], uv),
                "pushbroom": linear_lsq(Br, Bc, uv)}
        cells = "".join(f"{np.sqrt((e ** 2).mean()):>7.3f}/{e.max():<5.2f}" for e in errs.values())
        print(f"{name:<12}{cam.width:>5}x{cam.height:<5}  {cells}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
