"""What a bend correction found, in one shape for all of them."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Generic, TypeVar

import numpy as np


W = TypeVar("W")     # the warp's type: geometry.enu_map.BendWarp or EnuWarp


@dataclass(frozen=True)
class BendFit(Generic[W]):
    """One correction's result: its warp (None when it stands aside: `reason` says why), the
    summary the report gives (with "applied" and, when it stood aside, "reason"), and the H_A
    that goes with the warp when the correction refits one (the GCP and DEM bends; the metric
    bend step leaves the refit to the upgrade)."""

    warp: W | None                   # geometry.enu_map.BendWarp (affine frame) or EnuWarp (ENU)
    summary: dict
    H: np.ndarray | None = None

    @property
    def applied(self) -> bool:
        return self.warp is not None

    @property
    def reason(self) -> str:
        return self.summary.get("reason", "")
