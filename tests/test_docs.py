"""The docs site builds with no warning (MkDocs, strict), and every docs page or heading the
code cites exists; no machine path in the tree."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"


def test_the_docs_build_without_a_warning(tmp_path):
    pytest.importorskip("mkdocs")
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-q", "-d", str(tmp_path / "site")],
                       cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    assert (tmp_path / "site" / "configuration" / "index.html").exists()


def test_the_generated_reference_pages_are_committed_fresh():
    """docs/cli.md, configuration.md and method.md carry their generated blocks in the
    repository (a reader of a clone or a forge sees them): they must be what the code makes now
    (`python -m recon_core.docs_reference` writes them)."""
    from recon_core.docs_reference import GENERATED, refresh

    seen = set()
    for page in DOCS.glob("*.md"):
        text = page.read_text()
        assert refresh(text) == text, f"{page.name} is stale: run python -m recon_core.docs_reference"
        seen |= {k for k in GENERATED if f"<!-- end generated: {k} -->" in text}
    assert seen == set(GENERATED)


def test_the_built_site_holds_no_hook_code(tmp_path):
    pytest.importorskip("mkdocs")
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "-q", "-d", str(tmp_path / "site")],
                       cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    assert not list((tmp_path / "site").rglob("hooks.py"))


def test_every_document_the_code_names_is_in_the_repository():
    """A docstring or comment that names a document (docs/PAGE.md, or a NOTES-like file of
    capitals) names one of this repository: a reader must be able to open it."""
    names = re.compile(r"\bdocs/([\w-]+\.md)\b|\b([A-Z][A-Z_]{3,}(?:\.md)?)\b")
    shared = {"GEOMETRY_NOTES", "VIEWER_NOTES", "ARCHITECTURE", "STYLE", "SITE_FORMAT"}
    for f in list((ROOT / "recon_core").rglob("*.py")) + list((ROOT / "aerec_viewer").rglob("*.py")):
        for m in names.finditer(f.read_text()):
            if m.group(1):
                assert (DOCS / m.group(1)).exists(), f"{f}: names docs/{m.group(1)}, which does not exist"
            elif m.group(2).removesuffix(".md") in shared:
                raise AssertionError(f"{f}: names {m.group(2)}, a file outside the repository")


def _headings(page: Path) -> set[str]:
    return {m.group(1).strip().strip("`") for m in re.finditer(r"^#+ (.+)$", page.read_text(), re.M)}


def test_every_docs_citation_in_the_code_exists():
    """Code cites docs as (docs: PAGE.md, "Heading") or (docs: "Heading") for the page of its
    subject; each page and heading must exist. The README is cited only for its commands."""
    pages = {p.name: _headings(p) for p in DOCS.glob("*.md")}
    every = set().union(*pages.values())
    cited = 0
    for f in list((ROOT / "recon_core").rglob("*.py")) + list((ROOT / "aerec_viewer").rglob("*.py")) \
            + list((ROOT / "bench").glob("*.py")):
        text = f.read_text()
        assert not re.search(r"README[,:]? \"", text), f"{f}: cites a README section; cite the docs"
        for m in re.finditer(r"docs: (?:([\w-]+\.md),? ?)?(?:\"([^\"]+)\")?", text):
            page, heading = m.group(1), m.group(2)
            if page:
                assert page in pages, f"{f}: cites docs/{page}, which does not exist"
            if heading:
                assert heading in (pages[page] if page else every), f"{f}: cites the docs heading {heading!r}"
            cited += 1
    assert cited > 0


def test_no_machine_path_in_the_tree():
    # (built from parts, so this file does not match itself)
    pat = re.compile("/" + "work/|/home/\\w+/|/" + "root/|\\.\\./shared/[A-Z_]+\\.md")
    for f in ROOT.rglob("*"):
        if f.is_dir() or ".git" in f.parts or ".venv" in f.parts or "build" in f.parts \
                or f.suffix not in (".py", ".md", ".toml", ".yml", ".txt"):
            continue
        for k, line in enumerate(f.read_text(errors="replace").splitlines(), 1):
            assert not pat.search(line), f"{f.relative_to(ROOT)}:{k}: a machine path: {line.strip()}"


def test_every_value_fixed_in_the_code_says_what_it_is_and_why():
    """A module-level numeric constant of the library is a value a reader cannot change from the
    configuration: it must carry a comment (the docs' table of fixed values is made from them)."""
    from recon_core.docs_reference import constants_reference, module_constants

    rows = module_constants()
    assert len(rows) > 20                       # the scan sees the library's constants
    silent = [f"{m}.{n}" for m, n, _, c in rows if len(c) < 10]
    assert not silent, f"constants without a comment: {silent}"
    names = {n for _, n, _, _ in rows}
    assert {"MAX_FOCAL_SHARE", "CE90_FACTOR", "TIE_REFERENCE_VIEWS"} <= names
    assert all(f"`{n}`" in constants_reference() for n in names)


def test_every_option_of_every_command_says_what_it_does():
    import argparse

    from recon_core.cli import build_parser

    parser = build_parser()
    subs = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name, sp in subs.choices.items():
        for a in sp._actions:
            if isinstance(a, argparse._HelpAction):
                continue
            assert a.help, f"aerec {name}: {', '.join(a.option_strings) or a.dest} has no help text"


def test_every_default_a_docstring_names_is_the_configurations():
    """Where the code's text says what a parameter is by default ("off by default
    (SfmConfig.tie_sigma_px = 0)", "sfm.bend_step = true by default"), the value is the
    configuration's default: a default changed in config.py cannot leave its old value in the
    prose."""
    from recon_core.config import Config

    cfg = Config().to_dict()
    sections = {k.lower(): k for k in cfg if isinstance(cfg[k], dict)}
    name = r"(?:(?P<cls>[A-Z][A-Za-z]*)Config|(?P<sec>" + "|".join(sections) + r"))\.(?P<field>[a-z_0-9]+)"
    value = r"\s*=\s*(?P<val>-?[0-9.]+(?:e-?[0-9]+)?|true|false|True|False)\b"
    pattern = re.compile(r"default[^.\n]{0,60}?" + name + value + "|" + name.replace("?P<", "?P<b_") + value.replace(
        "?P<val>", "?P<b_val>") + r"[^.\n]{0,30}?by default")
    root = Path(__file__).resolve().parents[1]
    found, wrong = 0, []
    for p in sorted([*root.joinpath("recon_core").rglob("*.py"), *root.joinpath("aerec_viewer").rglob("*.py")]):
        text = p.read_text()
        for m in pattern.finditer(text):
            g = {k.removeprefix("b_"): v for k, v in m.groupdict().items() if v is not None}
            sec = g.get("sec") or sections.get((g.get("cls") or "").lower())
            if sec is None or g["field"] not in cfg[sec]:
                wrong.append(f"{p.name}: {m.group(0)!r} names no parameter")
                continue
            found += 1
            said = {"true": True, "false": False}.get(g["val"].lower(), None)
            said = float(g["val"]) if said is None else said
            have = cfg[sec][g["field"]]
            if (said != have) if isinstance(have, bool) else (float(have) != said):
                wrong.append(f"{p.name}: says {sec}.{g['field']} = {g['val']} by default; config.py has {have!r}")
    assert found >= 1 and not wrong, wrong
