"""Image windows for display: read decimated by window (never whole), tone-mapped to 8 bit."""

from __future__ import annotations

import math
import threading
from functools import lru_cache

import numpy as np

from recon_core.io.site import read_window
from recon_core.model.tiling import Window


class ImageSource:
    """Reads display textures of a site's images with one shared tone curve (thread-safe)."""

    def __init__(self, images: list, extra=()):
        self.images = {im.name: im for im in images}
        self.extra = {im.name: im for im in extra}     # shown, but not the site's (a reference orthoimage)
        self._tone = None
        self._lock = threading.Lock()

    def info(self, name: str):
        """The ImageInfo of a site image or of an extra one."""
        return self.images[name] if name in self.images else self.extra[name]

    @property
    def tone(self):
        with self._lock:
            if self._tone is None:
                from recon_core.sparse.features import tone_curve_for

                self._tone = tone_curve_for(list(self.images.values()))
            return self._tone

    CONTRAST = ("site", "image", "window")

    def read(self, win: Window, max_side: int, contrast: str = "site") -> np.ndarray:
        """(h, w) uint8 texture of a window, decimated so that its longer side <= max_side.

        contrast: "site" one tone curve for all images (the scene's tiles match), "image" the
        image's own (a 16-bit image among others, or a dark one), "window" stretched on the
        window itself (the most contrast where the operator looks: a zoomed tile)."""
        if contrast not in self.CONTRAST:
            raise ValueError(f"contrast must be one of {self.CONTRAST}")
        return _read_cached(self, win, int(max_side), contrast)

    def image_tone(self, name: str):
        from recon_core.sparse.features import tone_curve_for

        return _image_tone(self, name) if name in self.images or name in self.extra else tone_curve_for([])

    def whole(self, name: str) -> Window:
        im = self.info(name)
        return Window(name, 0, 0, im.width, im.height)


@lru_cache(maxsize=64)
def _image_tone(src: ImageSource, name: str):
    from recon_core.sparse.features import tone_curve_for

    return tone_curve_for([src.info(name)])


@lru_cache(maxsize=256)
def _read_cached(src: ImageSource, win: Window, max_side: int, contrast: str = "site") -> np.ndarray:
    from recon_core.sparse.features import ToneCurve

    im = src.info(win.image)
    if win.image in src.extra and contrast == "site":
        contrast = "image"                  # the site's stretch is not the reference's
    f = max(1.0, max(win.width, win.height) / max_side)
    w, h = max(1, int(math.ceil(win.width / f))), max(1, int(math.ceil(win.height / f)))
    g = read_window(im, win.col0, win.row0, win.width, win.height, out_shape=(h, w))
    if contrast == "image":
        return _image_tone(src, win.image).apply(g)
    if contrast == "window":
        v = g[np.isfinite(g)]
        if v.size:
            lo, hi = np.percentile(v, (0.5, 99.5))
            return ToneCurve(float(lo), float(hi)).apply(g)
    return src.tone.apply(g)
