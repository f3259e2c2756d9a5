"""What a bend correction found, in one shape for all of them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class BendFit:
    """One correction's result: its warp (None when it stands aside: `reason` says why), the
    summary the report gives (with "applied" and, when it stood aside, "reason"), and the H_A
    that goes with the warp when the correction refits one (the GCP and DEM bends; the metric
    bend step leaves the refit to the upgrade)."""

    warp: object | None              # geometry.enu_map.BendWarp (affine frame) or EnuWarp (ENU)
    summary: dict
    H: np.ndarray | None = None

    @property
    def applied(self) -> bool:
        return self.warp is not None

    @property
    def reason(self) -> str:
        return self.summary.get("reason", "")
