"""MkDocs hook: the reference pages are generated from the code, so they cannot go stale.

`<!-- generated: configuration -->` becomes the table of every parameter (recon_core.config:
its section, name, default, rule and comment); `<!-- generated: cli -->` every `aerec` command
with its options (recon_core.cli's parser); `<!-- generated: chain -->` the method as it runs
(recon_core.method.CHAIN); `<!-- generated: constants -->` the values fixed in the code
(recon_core.docs_reference.module_constants)."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def on_page_markdown(markdown: str, page, config, files) -> str:
    from recon_core.docs_reference import (
        cli_reference,
        config_reference,
        constants_reference,
        method_chain,
    )

    for key, make in (("configuration", config_reference), ("cli", cli_reference), ("chain", method_chain),
                      ("constants", constants_reference)):
        tag = f"<!-- generated: {key} -->"
        if tag in markdown:
            markdown = markdown.replace(tag, make())
    return markdown
