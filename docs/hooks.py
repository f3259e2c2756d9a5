"""MkDocs hook: the reference pages' generated blocks (the command line, the configuration, the
method as it runs, the values fixed in the code) are committed in docs/ so that a reader of the
repository sees them; the build makes them anew from the code (recon_core.docs_reference.
refresh), and tests/test_docs.py fails when the committed ones are stale
(`python -m recon_core.docs_reference` writes them)."""

from __future__ import annotations


def on_page_markdown(markdown: str, page, config, files) -> str:
    from recon_core.docs_reference import refresh

    return refresh(markdown)
