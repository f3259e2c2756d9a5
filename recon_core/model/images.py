"""An acquisition as the model knows it: its file, size, radiometry and acquisition time (read
and checked by recon_core.io.site)."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path


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

    def to_dict(self) -> dict:
        return {"name": self.name, "width": self.width, "height": self.height,
                "bands": self.bands, "dtype": self.dtype, "nodata": self.nodata,
                "acquired": None if self.acquired is None else iso_utc(self.acquired),
                "time_source": self.time_source, "has_rpc": self.has_rpc}


def iso_utc(t: datetime) -> str:
    return t.astimezone(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
