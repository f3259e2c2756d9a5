"""What a run checks before any compute: the site, the stage names, the output folder, the
configuration, the images, the GCPs (where they are, what the upgrade will make of them), the
reference DEM and the memory. Bad input raises InputError naming the file (one line, exit 2 at
the command line); what is only worth saying comes back as warnings.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from recon_core.config import Config
from recon_core.errors import InputError
from recon_core.io.files import writable_folder
from recon_core.io.gcps import read_gcps_geojson, working_gcp_file
from recon_core.io.site import Site, load_site, refuse_blank
from recon_core.model.grouping import group_by_date
from recon_core.resume import STAGES, finished_stages


def load_checked(site_path, out, until, redo_from) -> tuple[Site, Path]:
    """The checked stage names and the loaded site; the output folder checked, not created."""
    for name in (until, redo_from):
        if name is not None and name not in STAGES:
            raise InputError(None, f"unknown stage {name!r}; stages are {', '.join(STAGES)}")
    site = load_site(site_path)
    out = Path(out)
    refuse_nested(site.root, out)
    if out.exists() and not out.is_dir():
        raise InputError(out, "output path exists and is not a folder")
    return site, out


def make_out(out: Path) -> Path:
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(out, f"cannot create the output folder ({exc.strerror or exc})") from None
    return out


def refuse_nested(site_root: Path, out: Path) -> None:
    """An output folder inside the site (its products would become inputs: a DSM in images/
    breaks every later run of the site) or a site inside the output folder: refused, naming
    both, before anything is written."""
    try:
        site_r, out_r = Path(site_root).resolve(), Path(out).resolve()
    except (RuntimeError, OSError) as exc:          # a symlink loop, a name too long
        raise InputError(out, f"cannot resolve the path ({getattr(exc, 'strerror', None) or exc})") from None
    if out_r == site_r or out_r.is_relative_to(site_r):
        raise InputError(out, f"is inside the site {site_root}: outputs would mix with its inputs; "
                              "choose an output folder outside it")
    if site_r.is_relative_to(out_r):
        raise InputError(out, f"holds the site {site_root}: a run writes and removes files in its "
                              "output folder; choose one that does not contain the site")


def check_config(cfg: Config, until: str | None = None) -> None:
    """Every parameter against the schema (recon_core.config.validate: type, range, finiteness,
    choices, relations between fields), and, for a run that reaches the dense stage (`until`
    None or later), the chosen matcher's optional packages; before any compute. Raises
    InputError naming the field (without a file: the caller names where the value came from)."""
    from recon_core.config import check_extras, validate

    try:
        validate(cfg)
        if until not in STAGES or STAGES.index(until) >= STAGES.index("dense"):
            check_extras(cfg)
    except ValueError as exc:
        raise InputError(None, str(exc)) from None


def check_images(site: Site) -> None:
    """What the images can be refused for before any compute beyond opening them: a blank one,
    and two that are one image (the same pixels where sampled: a copy under another name, which
    would end after the matching in a degenerate geometry that blamed neither)."""
    from recon_core.io.site import MIN_IMAGE_SIDE

    seen: dict[bytes, str] = {}
    for im in site.images:
        if min(im.width, im.height) < MIN_IMAGE_SIDE:
            raise InputError(im.path, f"{im.width} x {im.height} px: too small to match (at least "
                                      f"{MIN_IMAGE_SIDE} px a side)")
        v = refuse_blank(im)
        key = hashlib.sha1(np.ascontiguousarray(v, np.float64).tobytes()
                           + f"{im.width}x{im.height}".encode()).digest()
        if key in seen:
            raise InputError(im.path, f"is the same image as {seen[key]} (the same pixels): two views of "
                                      "one acquisition give no parallax; keep one of them")
        seen[key] = im.name


def preflight(site_path: str | Path, out: str | Path, cfg: Config, until: str | None = None,
              redo_from: str | None = None) -> list[str]:
    """What can be checked before any compute, for a run that should reach `until`: the site
    (load_site validates images, times, GCP file, site.json), the stage names, the output
    folder (creatable and writable), and, when the run goes as far as the upgrade, GCPs: at
    least one date group must have the control GCPs its upgrade needs
    (recon_core.euclidean.control). Raises InputError; returns warnings (a group that will not be upgraded)."""
    check_config(cfg, until)
    site, out = load_checked(site_path, out, until, redo_from)
    check_images(site)
    check_reference_dem(site, cfg)
    from recon_core.memory import check_memory

    todo = STAGES[: STAGES.index(until) + 1] if until else STAGES
    if Path(out).is_dir() and redo_from is None:     # what a resumed run will not compute again
        done = finished_stages(Path(out), cfg, site)
        first = next((k for k, s in enumerate(todo) if s not in done), len(todo))
        todo = todo[first:]
    elif redo_from is not None:
        todo = [s for s in todo if STAGES.index(s) >= STAGES.index(redo_from)]
    check_memory(site, cfg, todo)
    if "eval" in todo:
        from recon_core.evaluation.stage import reference_dsms

        for ref, what in [(site.gt_dsm, "ground-truth DSM"), *((p, "reference DSM") for p in reference_dsms(site.root))]:
            if ref is not None:
                check_pixels_readable(ref, what)
    early = check_groups(site, cfg)
    if cfg.dsm.resolution_m and site.hints.get("bounds"):
        from recon_core.io.site import check_grid_size

        check_grid_size(None, site.hints["bounds"], cfg.dsm.resolution_m)
    out = make_out(out)
    writable_folder(out, create=False)
    if STAGES.index(until or STAGES[-1]) < STAGES.index("upgrade"):
        return early
    gcp_path = working_gcp_file(site.root, out)
    gcps = site.gcps if gcp_path == site.root / "gcps.geojson" else read_gcps_geojson(
        gcp_path, {im.name: im for im in site.images})
    refuse_far_gcps(gcp_path, gcps)
    refuse_gcps_off_the_images(gcp_path, gcps, site)
    notes = early + ([] if (w := gcp_file_note(site.root, out)) is None else [w])
    if not gcps:
        csv = sorted(site.root.glob("*.csv"))
        hint = (f"; {csv[0].name} is not read: `aerec gcps convert {csv[0]} {site.root / 'gcps.geojson'}`"
                if csv and not (site.root / "gcps.geojson").exists() else "")
        from recon_core.euclidean.control import need_words

        raise InputError(gcp_path, f"no GCP: the Euclidean upgrade needs {need_words()} of each date group "
                                   "(stop before it with --stage dense)" + hint)
    groups = group_by_date(site.images, cfg.grouping.max_gap_days, cfg.grouping.max_span_days)
    warnings, ok, flat = [], [], []
    for level, g, text in gcp_findings(groups, gcps, cfg):
        if level == "error":
            flat.append((g, text))
        elif level == "ok":
            ok.append(g)
        elif level == "joint":          # upgradable if the joint reconstruction happens
            ok.append(g)
            warnings.append(text)
        else:
            warnings.append(text)
    if flat and not ok:            # nothing could be upgraded: refuse, naming the first flat group
        raise InputError(gcp_path, f"group {flat[0][0]}: {flat[0][1]}")
    warnings += [f"group {g} will not be upgraded: {text}" for g, text in flat]
    if not ok:
        raise InputError(gcp_path, "no date group has enough control GCPs observed in >= 2 of its images: "
                                   + "; ".join(warnings) + " (stop before the upgrade with --stage dense)")
    if cfg.upgrade.reference_dem:
        from recon_core.bend.dem import check_covers, open_reference_dem

        check_covers(open_reference_dem(cfg.upgrade.reference_dem),
                     np.array([g.llh for g in gcps if g.role == "control" and g.enabled]).reshape(-1, 3))
    return notes + warnings


def check_pixels_readable(path: Path, what: str, side: int = 1024) -> None:
    """A raster the run will read at its end, read now at most `side` px a side: a truncated or
    damaged file is refused before the compute, not after it."""
    import rasterio
    import rasterio.errors

    try:
        with rasterio.open(path) as src:
            f = max(1, int(np.ceil(max(src.width, src.height) / side)))
            src.read(1, out_shape=(max(1, src.height // f), max(1, src.width // f)))
    except rasterio.errors.RasterioIOError as exc:
        raise InputError(path, f"cannot read the {what}'s pixels (a truncated or damaged file?): "
                               f"{exc.__cause__ or exc}") from None


def check_reference_dem(site: Site, cfg: Config, gcps=None) -> None:
    """upgrade.reference_dem, whatever stage the run stops at: a DEM GDAL reads, with heights,
    where the site is (recon_core.euclidean.ground_reference.check_reference_files)."""
    if not cfg.upgrade.reference_dem:
        return
    from recon_core.bend.dem import open_reference_dem
    from recon_core.euclidean.ground_reference import check_reference_files

    check_reference_files(site, gcps, dem=open_reference_dem(cfg.upgrade.reference_dem),
                          dem_option="upgrade.reference_dem")


MAX_GCP_SPREAD_M = 100_000.0     # a scene of any satellite is smaller: a GCP farther from the others
                                 # has wrong coordinates (a sign, a digit, a swapped lon/lat)


def refuse_far_gcps(path: Path, gcps: list) -> None:
    """A GCP far from the others (more than any scene spans) is refused, naming it: its
    coordinates are wrong, and a DSM fitted to it would lie elsewhere."""
    from recon_core.euclidean.georef import frame_for

    used = [g for g in gcps if g.enabled]
    if len(used) < 2:
        return
    enu = frame_for(used).geodetic_to_enu(np.array([g.llh for g in used]))
    d = np.linalg.norm(enu[:, :2] - np.median(enu[:, :2], axis=0), axis=1)
    k = int(np.argmax(d))
    if d[k] > MAX_GCP_SPREAD_M:
        raise InputError(path, f"GCP {used[k].id} is {d[k] / 1000:,.0f} km from the others (lon "
                               f"{used[k].lon:.6f}, lat {used[k].lat:.6f}): its coordinates are wrong "
                               "(a sign, a digit, lon and lat swapped?)")


MAX_GCP_OFF_IMAGES_M = 10_000.0   # a GCP farther than this outside every image's footprint is not of
                                  # this site (wrong coordinates): the footprints' own error is metres


def refuse_gcps_off_the_images(path: Path, gcps: list, site: Site) -> None:
    """GCPs, footprints and RPCs must agree on where the site is: a GCP farther than
    MAX_GCP_OFF_IMAGES_M outside every image's footprint (from the images' RPCs, when they have
    some) is refused, naming it, and saying so when its lon and lat swapped would fall inside."""
    from recon_core.io.footprints import image_footprints, off_the_images

    used = [g for g in gcps if g.enabled]
    if not used:
        return
    foot = image_footprints(site)
    if not foot:
        return
    d = off_the_images(np.array([[g.lon, g.lat] for g in used]), foot)
    k = int(np.argmax(d))
    if d[k] <= MAX_GCP_OFF_IMAGES_M:
        return
    g = used[k]
    swapped = abs(g.lon) <= 90 and off_the_images(np.array([[g.lat, g.lon]]), foot)[0] <= MAX_GCP_OFF_IMAGES_M
    raise InputError(path, f"GCP {g.id} (lon {g.lon:.6f}, lat {g.lat:.6f}) lies {d[k] / 1000:,.0f} km from "
                           "every image's footprint (from the images' RPCs, read for this check only): "
                           + ("its lon and lat are swapped" if swapped else "its coordinates are wrong")
                           + (f"; {int(np.sum(d > MAX_GCP_OFF_IMAGES_M))} of {len(used)} GCPs are off the images"
                              if np.sum(d > MAX_GCP_OFF_IMAGES_M) > 1 else ""))


def check_groups(site: Site, cfg: Config) -> list[str]:
    """Date groups of one image cannot be reconstructed (no parallax within a date): refused
    when every group is one, else a warning naming them."""
    groups = group_by_date(site.images, cfg.grouping.max_gap_days, cfg.grouping.max_span_days)
    single = [g for g in groups if len(g.images) < 2]
    if single and len(single) == len(groups):
        raise InputError(site.root / "images", f"{'the site has one image' if len(site.images) < 2 else 'every date group has one image'}"
                                               f" ({', '.join(im.name for im in site.images[:6])}"
                                               f"{', ...' if len(site.images) > 6 else ''}): the method needs 2 "
                                               "or more views of one date (grouping.max_gap_days, max_span_days)")
    return [f"group {g.index} ({g.images[0].name}) has one image: it will not be reconstructed "
            "(one view has no parallax)" for g in single]


def gcp_findings(groups, gcps, cfg: Config) -> list[tuple[str, int, str]]:
    """Per date group, what the upgrade will make of the GCPs, from the GCP file alone:
    ("ok" | "joint" | "warning" | "error", group, text). A warning: fewer usable control GCPs
    than it needs (4, or 3 when the images state their viewing directions: the group is not
    upgraded); "joint": fewer of its own but enough over all the groups' images (upgraded only if
    the groups are reconstructed jointly); an error: a control set that nothing can make fix the
    height scale (the upgrade would refuse that group; the run refuses when no group is left)."""
    from recon_core.euclidean.control import MIN_CONTROL_HELD, control_needed, usable_before_models
    from recon_core.model.grouping import tries_joint

    out = []
    joint = None
    every = [im for g in groups for im in g.images]
    if tries_joint(groups, cfg):
        # the groups will share one frame and one upgrade when they match across dates: a GCP
        # then counts when it is seen in >= 2 images of any groups
        names = {im.name for im in every}
        joint = [p for p in gcps if any(usable_before_models(p, names, g.index) for g in groups)]
    for g in groups:
        names = {im.name for im in g.images}
        usable = [p for p in gcps if usable_before_models(p, names, g.index)]
        n, need = len(usable), control_needed(g.images, cfg)
        if n < need and joint is not None and len(joint) >= control_needed(every, cfg):
            held = control_needed(every, cfg) == MIN_CONTROL_HELD
            refusal = None if cfg.upgrade.allow_flat_gcps else _flat_control_refusal(joint, held)
            if refusal:
                out.append(("error", g.index, refusal))
            else:
                out.append(("joint", g.index, f"group {g.index} ({', '.join(sorted(names))}): {n} control "
                            f"GCP(s) observed in >= 2 of its images, {need} needed on its own: it will be "
                            f"upgraded only with the other date groups, through the joint reconstruction "
                            f"({len(joint)} control GCPs over all images), which needs the groups to match "
                            "across dates (sfm.joint_groups)"))
            continue
        if n < need:
            out.append(("warning", g.index, f"group {g.index} ({', '.join(sorted(names))}): {n} control "
                        f"GCP(s) observed in >= 2 of its images, {need} needed"
                        + ("" if need == MIN_CONTROL_HELD else
                           f" ({MIN_CONTROL_HELD} when its images state their viewing directions)")
                        + ": it will not be upgraded"))
            continue
        refusal = None if cfg.upgrade.allow_flat_gcps else _flat_control_refusal(usable, need == MIN_CONTROL_HELD)
        if refusal:
            out.append(("error", g.index, refusal))
        else:
            out.append(("ok", g.index, f"group {g.index}: {n} control GCPs usable"))
    return out


def gcp_file_note(site_root: Path, out: Path) -> str | None:
    """A warning when OUT/gcps.geojson (the viewer's working set, which a run on OUT uses) and
    the site's gcps.geojson differ and the site's was edited after it: which one is used and how
    to use the other."""
    own, site_file = Path(out) / "gcps.geojson", Path(site_root) / "gcps.geojson"
    if not (own.exists() and site_file.exists()):
        return None
    if site_file.stat().st_mtime <= own.stat().st_mtime:
        return None
    def key(path):
        return sorted((g.id, round(g.lon, 9), round(g.lat, 9), round(g.h, 4), g.role, g.enabled,
                       tuple(sorted((k, tuple(np.round(v, 4))) for k, v in g.observations.items())))
                      for g in read_gcps_geojson(path))

    try:
        if key(own) == key(site_file):
            return None
    except InputError:
        pass
    return (f"{site_file} was edited after {own} (the working GCP set, e.g. the viewer's): the run "
            f"uses {own}, not the site's file; delete {own} to use the site's GCPs")


# the best a GCP's affine height is known to: the pre-flight refuses only what the fit would
# refuse even so (the fit decides the rest from the triangulation covariances)
PREFLIGHT_GCP_SIGMA_M = 0.1


def _flat_control_refusal(control: list, held: bool = False) -> str | None:
    """The upgrade's refusal of a control set that nothing can make fix the height scale, from
    the GCPs' ground coordinates alone (so before any compute): collinear GCPs always; without
    the images' viewing directions (`held` False), GCPs so near one plane that even an optimistic
    triangulation (PREFLIGHT_GCP_SIGMA_M) leaves the height scale undetermined."""
    from recon_core.euclidean.georef import frame_for
    from recon_core.euclidean.upgrade import conditioning, flat_gcp_refusal, on_one_line

    frame = frame_for(control)
    enu = frame.geodetic_to_enu(np.array([p.llh for p in control]))
    if len(enu) >= 2 and on_one_line(enu):
        return (f"refused: the {len(enu)} control GCPs ({', '.join(p.id for p in control)}) lie on one line: "
                "nothing fixes H_A across it; add a GCP off that line")
    if held:
        return None
    return flat_gcp_refusal(conditioning(enu, PREFLIGHT_GCP_SIGMA_M))
