"""The Euclidean cloud as LAS/LAZ with its CRS, for PDAL, QGIS, CloudCompare and lidar tools.

`cloud.ply` stays the project's own copy (docs: site-format.md); `cloud.laz` is written from it by
chunks after the DSM stage: LAS 1.4, point format 7 (x, y, z, RGB), coordinates in millimetres
(scale 0.001 m) with the offset at the cloud's first chunk, the horizontal CRS as an OGC WKT
VLR, and heights above the WGS84 ellipsoid (said in the header's system identifier and in a
text VLR: a LAS CRS names no ellipsoidal vertical datum for a projected CRS).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from recon_core.io.files import atomic_path
from recon_core.io.ply import open_ply, ply_fields

HEIGHTS_NOTE = "z: height above the WGS84 ellipsoid (m), not above the geoid"


def write_las(ply: str | Path, path: str | Path, epsg: int, chunk: int = 4_000_000) -> int:
    """Convert a Euclidean PLY (x y in the projected CRS `epsg`, z ellipsoidal h) to `path`
    (.laz compressed, .las not), atomically; returns the number of points."""
    import laspy
    import pyproj

    path = Path(path)
    rec = open_ply(ply)
    header = laspy.LasHeader(point_format=7, version="1.4")
    header.scales = np.array([0.001, 0.001, 0.001])
    first = ply_fields(rec[:min(len(rec), 100_000)])[0] if len(rec) else np.zeros((1, 3))
    header.offsets = np.floor(first.min(axis=0))
    header.add_crs(pyproj.CRS.from_epsg(int(epsg)))
    header.system_identifier = "AE-Rec, heights ellipsoidal"[:32]
    header.generating_software = "AE-Rec"[:32]
    header.vlrs.append(laspy.VLR(user_id="AE-Rec", record_id=1, description="vertical datum",
                                 record_data=HEIGHTS_NOTE.encode("ascii")))
    compress = path.suffix.lower() == ".laz"
    with atomic_path(path) as tmp:
        with laspy.open(tmp, mode="w", header=header, do_compress=compress) as w:
            for a in range(0, len(rec), chunk):
                xyz, colors, _ = ply_fields(rec[a:a + chunk])
                pts = laspy.ScaleAwarePointRecord.zeros(len(xyz), header=header)
                pts.x, pts.y, pts.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
                if colors is not None:
                    c16 = colors.astype(np.uint16) * 257
                    pts.red, pts.green, pts.blue = c16[:, 0], c16[:, 1], c16[:, 2]
                w.write_points(pts)
    return len(rec)
