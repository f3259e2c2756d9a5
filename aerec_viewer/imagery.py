"""Image windows for display: read decimated by window (never whole), tone-mapped to 8 bit."""

from __future__ import annotations

import math
import threading
import warnings
from dataclasses import dataclass
from functools import lru_cache

import numpy as np


@dataclass(frozen=True)
class ImageWindow:
    """A window of a full image, in full-image pixels: columns col0 .. col0 + width - 1."""

    image: str
    col0: int
    row0: int
    width: int
    height: int

    def pixel(self, fx: float, fy: float) -> tuple[float, float]:
        """Fractions of the window (0 = left/top edge, 1 = right/bottom edge) -> full-image
        (col, row), centre of the top-left pixel at (0, 0) (SITE_FORMAT)."""
        return self.col0 - 0.5 + fx * self.width, self.row0 - 0.5 + fy * self.height

    def fraction(self, col: float, row: float) -> tuple[float, float]:
        """Inverse of `pixel`."""
        return (col - self.col0 + 0.5) / self.width, (row - self.row0 + 0.5) / self.height

    def contains(self, col: float, row: float) -> bool:
        fx, fy = self.fraction(col, row)
        return 0.0 <= fx <= 1.0 and 0.0 <= fy <= 1.0


class ImageSource:
    """Reads display textures of a site's images with one shared tone curve (thread-safe)."""

    def __init__(self, images: list):
        self.images = {im.name: im for im in images}
        self._tone = None
        self._lock = threading.Lock()

    @property
    def tone(self):
        with self._lock:
            if self._tone is None:
                from recon_core.features import tone_curve_for

                self._tone = tone_curve_for(list(self.images.values()))
            return self._tone

    def read(self, win: ImageWindow, max_side: int) -> np.ndarray:
        """(h, w) uint8 texture of a window, decimated so that its longer side <= max_side."""
        return _read_cached(self, win, int(max_side))

    def whole(self, name: str) -> ImageWindow:
        im = self.images[name]
        return ImageWindow(name, 0, 0, im.width, im.height)


@lru_cache(maxsize=256)
def _read_cached(src: ImageSource, win: ImageWindow, max_side: int) -> np.ndarray:
    import rasterio
    from rasterio.enums import Resampling
    from rasterio.errors import NotGeoreferencedWarning
    from rasterio.windows import Window

    from recon_core.site import to_gray_float

    im = src.images[win.image]
    f = max(1.0, max(win.width, win.height) / max_side)
    w, h = max(1, int(math.ceil(win.width / f))), max(1, int(math.ceil(win.height / f)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        with rasterio.open(im.path) as ds:
            a = ds.read(window=Window(win.col0, win.row0, win.width, win.height),
                        out_shape=(ds.count, h, w), resampling=Resampling.average)
    g = to_gray_float(a)
    if im.nodata is not None and not np.isnan(im.nodata):
        g[np.any(a == im.nodata, axis=0)] = np.nan
    return src.tone.apply(g)
