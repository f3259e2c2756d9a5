"""What the stages of a run pass on to each other (reloaded from OUT when a stage resumes)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple, Protocol

from recon_core.config import Config
from recon_core.geometry.enu_map import EnuMap
from recon_core.geometry.geodesy import LocalFrame
from recon_core.io.gcps import GCP
from recon_core.io.layout import OutLayout
from recon_core.io.site import Site
from recon_core.model.grouping import Group
from recon_core.model.sparse_model import SparseModel

if TYPE_CHECKING:
    from recon_core.events import EventBus


class UpgradeMaps(NamedTuple):
    """What the upgrade hands on: each group's whole map to the shared ENU frame, and that frame."""

    maps: dict[int, EnuMap]
    frame: LocalFrame


@dataclass
class RunState:
    """The state of one run.

    Attributes:
        site: the input site; gcps: the GCP set the run uses (the working set OUT/gcps.geojson
        when it exists, else the site's); out: the output folder (layout: its files).
        models: group -> SparseModel; dense: group -> dense.ply path;
        upgrade: UpgradeMaps once upgraded; report: report.json's content.
    """

    site: Site
    out: Path
    cfg: Config
    groups: list[Group]
    gcps: list[GCP] = field(default_factory=list)
    gcp_file: Path | None = None      # the GCP file the run read (the working set or the site's)
    gcp_text: str = ""                # its content at the start of the run (the stages' hashes)
    models: dict[int, SparseModel] = field(default_factory=dict)
    dense: dict[int, Path] = field(default_factory=dict)
    upgrade: UpgradeMaps | None = None
    report: dict = field(default_factory=dict)

    @property
    def layout(self) -> OutLayout:
        return OutLayout(self.out)


class Stage(Protocol):
    """A stage of the pipeline (recon_core.pipeline.STAGE_MODULES): computes its products from
    the state and returns its summary, or reloads them from OUT into the state."""

    def run(self, state: RunState, bus: EventBus) -> dict: ...

    def load(self, state: RunState) -> None: ...
