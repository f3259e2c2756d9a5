"""The generator's true orthoimage (recon_core.synthetic.generator.render_ortho), the reference
orthoimage of bench_operator's run without a survey."""

from __future__ import annotations

import numpy as np


def test_the_true_orthoimage_lies_on_the_truth_dsm(tiny_site, tmp_path):
    """render_ortho: the scene from straight above on the truth DSM's grid; its edges (roofs,
    tree crowns) fall on the DSM's height steps: their cross-correlation peaks at no shift."""
    import cv2
    import rasterio

    from recon_core.synthetic.generator import render_ortho

    path = render_ortho(tiny_site, tmp_path / "ortho.tif", "tiny", 0)
    with rasterio.open(path) as o, rasterio.open(tiny_site / "gt_dsm.tif") as g:
        assert o.transform == g.transform and o.crs == g.crs and o.dtypes[0] == "uint16"
        img, dsm, nd = o.read(1).astype(np.float32), g.read(1), g.nodata
    ok = dsm != nd
    dsm = np.where(ok, dsm, np.median(dsm[ok])).astype(np.float32)

    def edges(a):
        return np.hypot(cv2.Sobel(a, cv2.CV_32F, 1, 0), cv2.Sobel(a, cv2.CV_32F, 0, 1))

    e_img, e_dsm = edges(img), np.minimum(edges(dsm), 20.0)
    inner = (slice(40, -40), slice(40, -40))
    res = cv2.matchTemplate(e_img, e_dsm[inner], cv2.TM_CCORR_NORMED)
    _, _, _, loc = cv2.minMaxLoc(res)
    assert loc == (40, 40), loc
