"""An acquisition as the model knows it: its file, size, radiometry, acquisition time and, when
its metadata states it, its viewing direction (read and checked by recon_core.io.site)."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path


@dataclass(frozen=True)
class ViewAngles:
    """The viewing direction at the image centre as the vendor's metadata states it (the site
    format's optional sidecar member `view`): incidence from the local vertical to the direction
    of the satellite, and that direction's azimuth, clockwise from north (degrees)."""

    incidence_deg: float
    azimuth_deg: float

    def to_dict(self) -> dict:
        return {"incidence_deg": self.incidence_deg, "azimuth_deg": self.azimuth_deg}


@dataclass
class ImageInfo:
    """One acquisition: file, size, radiometry and acquisition time (UTC)."""

    name: str
    path: Path
    width: int
    height: int
    bands: int
    dtype: str
    nodata: float | None
    acquired: datetime | None
    time_source: str
    has_rpc: bool
    view: ViewAngles | None = None      # the sidecar's `view`, when it has one

    def to_dict(self) -> dict:
        d = {"name": self.name, "width": self.width, "height": self.height,
             "bands": self.bands, "dtype": self.dtype, "nodata": self.nodata,
             "acquired": None if self.acquired is None else iso_utc(self.acquired),
             "time_source": self.time_source, "has_rpc": self.has_rpc}
        if self.view is not None:
            d["view"] = self.view.to_dict()
        return d


def iso_utc(t: datetime) -> str:
    return t.astimezone(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
