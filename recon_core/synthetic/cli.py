"""`aerec synth`: write a synthetic site, registered through the `aerec.commands` entry point so
that the reconstruction's command line never imports the generator."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

PRESET_NAMES = ("tiny", "tiny2", "tiny2fp", "mini", "quick", "demo", "demofp", "flat", "large", "wide", "wide3")   # recon_core.synthetic.generator.PRESETS


def cmd_synth(args) -> int:
    from recon_core.cli import ProgressPrinter
    from recon_core.synthetic.generator import generate_site

    t0 = time.time()
    prog = ProgressPrinter(not args.quiet)
    generate_site(args.out, preset=args.preset, seed=args.seed, progress=prog)
    prog.close()
    print(f"wrote {args.preset} site (seed {args.seed}) to {args.out} in {time.time() - t0:.1f} s")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    s = sub.add_parser("synth", help="write a synthetic pushbroom site with known truth")
    s.add_argument("out", type=Path, help="site folder to write")
    s.add_argument("--preset", default="demo", choices=PRESET_NAMES)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=cmd_synth)
