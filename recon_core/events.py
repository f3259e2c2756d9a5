"""Events the pipeline emits. The core never knows who listens (CLI progress, viewer, tests).

Events are small immutable records; arrays inside them are owned by the event (copies), so a
listener on another thread may keep them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np


@dataclass(frozen=True)
class StageProgress:
    stage: str                   # "features", "matching", "sfm", "dense", "upgrade", "dsm", ...
    done: int
    total: int
    message: str = ""
    group: int | None = None


@dataclass(frozen=True)
class StageStarted:
    """A pipeline stage begins computing (not emitted for a stage reloaded from OUT): whoever
    reports a failure can name the stage that was running."""

    stage: str                   # one of recon_core.pipeline.STAGES


@dataclass(frozen=True)
class StageDone:
    stage: str
    seconds: float
    summary: dict = field(default_factory=dict)
    group: int | None = None


@dataclass(frozen=True)
class TileRegistered:
    group: int
    tile_id: str
    image: str
    camera: np.ndarray           # (2, 4) affine camera, full-image pixels
    footprint: np.ndarray        # (4, 3) tile corners back-projected onto its points' plane (affine frame)
    n_inliers: int
    order: int                   # 0-based registration order
    total_tiles: int


@dataclass(frozen=True)
class PointsAdded:
    group: int
    ids: np.ndarray              # (n,) point ids, unique within the group
    xyz: np.ndarray              # (n, 3) affine-frame coordinates
    rgb: np.ndarray              # (n, 3) uint8 colours
    n_views: np.ndarray          # (n,) number of observations
    reproj_px: np.ndarray        # (n,) RMS reprojection error
    kind: str = "sparse"         # "sparse" or "dense"


@dataclass(frozen=True)
class ModelUpdated:
    """Whole sparse model after a bundle adjustment: all cameras and points, replacing earlier ones."""

    group: int
    cameras: dict                # tile_id -> (2, 4)
    footprints: dict             # tile_id -> (4, 3)
    ids: np.ndarray
    xyz: np.ndarray
    rgb: np.ndarray
    n_views: np.ndarray
    reproj_px: np.ndarray


@dataclass(frozen=True)
class BundleAdjusted:
    group: int
    scope: str                   # "local" or "global"
    cost_before: float
    cost_after: float
    rms_px: float
    n_cameras: int
    n_points: int
    seconds: float
    repeat: bool = False         # a joint reconstruction's adjustment told again to another of
    #                              its groups: count it once (time, runs)


@dataclass(frozen=True)
class Message:
    level: str                   # "info", "warning", "error"
    text: str
    group: int | None = None


@dataclass
class ModelsReady:
    """The sparse models of every reconstructed group (group -> SparseModel), once the sparse
    stage has computed or reloaded them: GCP tools and the upgrade need them while the later
    stages still run. Listeners must treat the models as read-only."""

    models: dict


Event = StageProgress | StageDone | TileRegistered | PointsAdded | ModelUpdated | BundleAdjusted | Message | ModelsReady
Listener = Callable[[object], None]


class EventBus:
    """Fan out events to listeners; a failing listener never breaks the pipeline."""

    def __init__(self, *listeners: Listener):
        self._listeners: list[Listener] = [l for l in listeners if l is not None]

    def subscribe(self, listener: Listener) -> None:
        self._listeners.append(listener)

    def emit(self, event: object) -> None:
        for listener in list(self._listeners):
            try:
                listener(event)
            except Exception as exc:  # a listener's bug must not kill a long reconstruction
                import logging

                logging.getLogger("aerec").warning("event listener failed: %s", exc)

    def progress(self, stage: str, done: int, total: int, message: str = "", group: int | None = None) -> None:
        self.emit(StageProgress(stage, done, total, message, group))

    def message(self, text: str, level: str = "info", group: int | None = None) -> None:
        self.emit(Message(level, text, group))
