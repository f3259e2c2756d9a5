"""`aerec synth`: write a synthetic site, registered through the `aerec.commands` entry point so
that the reconstruction's command line never imports the generator."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

PRESET_NAMES = ("tiny", "tiny2", "tiny2fp", "mini", "minifp", "quick", "demo", "demofp", "flat", "flatfp", "large", "wide", "wide3")   # recon_core.synthetic.generator.PRESETS


def cmd_synth(args) -> int:
    """Write the site into a hidden folder beside OUT and rename it into place when it is whole:
    an interrupted run leaves no partial site, and a site is never written over another one's
    files (OUT must be new or empty)."""
    from recon_core.cli import ProgressPrinter
    from recon_core.errors import InputError
    from recon_core.io.files import atomic_folder
    from recon_core.synthetic.generator import generate_site

    from recon_core.io.files import writable_folder

    out = Path(args.out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputError(out, "exists and is not empty: a synthetic site is written into a new or "
                              "empty folder (remove it, or choose another)")
    parent = next((p for p in out.absolute().parents if p.exists()), None)
    if parent is not None and not parent.is_dir():
        raise InputError(parent, f"is a file, not a folder: {out} cannot be made under it")
    writable_folder(out.absolute().parent, create=True)
    t0 = time.time()
    prog = ProgressPrinter(not args.quiet)
    with atomic_folder(out) as tmp:
        generate_site(tmp, preset=args.preset, seed=args.seed, progress=prog)
        prog.close()
    print(f"wrote {args.preset} site (seed {args.seed}) to {out} in {time.time() - t0:.1f} s")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    s = sub.add_parser("synth", help="write a synthetic pushbroom site with known truth")
    s.add_argument("out", type=Path, help="site folder to write (new, or empty)")
    s.add_argument("--preset", default="demo", choices=PRESET_NAMES,
                   help="the site's layout and size (docs/synthetic.md)")
    s.add_argument("--seed", type=int, default=0, help="the seed of every random draw (same seed, same bytes)")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=cmd_synth)
