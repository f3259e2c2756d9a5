"""The reference pages of the docs, generated from the code (docs/hooks.py puts them in place):
every parameter with its default, rule and comment; every command with its options; the
method's chain. Generated, so they cannot go stale."""

from __future__ import annotations

import dataclasses
import inspect

from recon_core.config import field_comments


def _rule_text(rule) -> str:
    if rule.choices is not None:
        from recon_core.config import _choices

        return "one of " + ", ".join(f"`{c}`" for c in _choices(rule.choices))
    parts = []
    if rule.lo is not None:
        parts.append(f"{'>' if rule.lo_open else '>='} {rule.lo:g}")
    if rule.hi is not None:
        parts.append(f"{'<' if rule.hi_open else '<='} {rule.hi:g}")
    if rule.odd:
        parts.append("odd")
    return ", ".join(parts)


def _value(v) -> str:
    if v is None:
        return "(none)"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return f'"{v}"'
    if isinstance(v, tuple):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    return repr(v)


def config_reference() -> str:
    """Every parameter as `aerec config --dump` writes it, by section, with its rule."""
    from recon_core.config import RELATIONS, Config

    cfg = Config()
    lines = []
    top = [f for f in dataclasses.fields(cfg) if not dataclasses.is_dataclass(getattr(cfg, f.name))]
    for f in dataclasses.fields(cfg):
        sec = getattr(cfg, f.name)
        if not dataclasses.is_dataclass(sec):
            continue
        com = field_comments(type(sec))
        lines += [f"### [{f.name}]", ""]
        doc = inspect.getdoc(type(sec))
        if doc and not doc.startswith(type(sec).__name__ + "("):
            lines += [doc, ""]
        lines += ["| parameter | default | allowed | what it does |", "|---|---|---|---|"]
        for g in dataclasses.fields(sec):
            rule = g.metadata.get("rule")
            allowed = _rule_text(rule) if rule else ""
            text = com.get(g.name, "").replace("|", "\\|")
            lines.append(f"| `{g.name}` | `{_value(getattr(sec, g.name))}` | {allowed} | {text} |")
        lines.append("")
    if top:
        lines += ["### top level", "", "| parameter | default | allowed | what it does |", "|---|---|---|---|"]
        com = field_comments(Config)
        for g in top:
            rule = g.metadata.get("rule")
            lines.append(f"| `{g.name}` | `{_value(getattr(cfg, g.name))}` | "
                         f"{_rule_text(rule) if rule else ''} | {com.get(g.name, '')} |")
        lines.append("")
    lines += ["### Relations between parameters", ""]
    lines += [f"- {', '.join(f'`{n}`' for n in names)}: {need}" for names, _, need in RELATIONS]
    return "\n".join(lines) + "\n"


def cli_reference() -> str:
    """Every `aerec` command and its options, from the parser the command line uses."""
    import argparse

    from recon_core.cli import build_parser

    import os

    old = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = "100"           # argparse wraps usage lines to the terminal: a fixed width
    try:
        parser = build_parser()
        text = _cli_pages(parser, argparse)
    finally:
        if old is None:
            os.environ.pop("COLUMNS", None)
        else:
            os.environ["COLUMNS"] = old
    return text


def _cli_pages(parser, argparse) -> str:
    subs = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    helps = {a.dest: a.help for a in subs._choices_actions}
    lines = []
    for name, sp in subs.choices.items():
        lines += [f"### `aerec {name}`", "", helps.get(name) or "", "", "```text",
                  sp.format_usage().replace("usage: ", "").strip(), "```", ""]
        rows = []
        for a in sp._actions:
            if isinstance(a, argparse._HelpAction):
                continue
            flag = ", ".join(a.option_strings) or a.dest
            h = (a.help or "").replace("|", "\\|")
            if a.choices and not isinstance(a, argparse._SubParsersAction):
                h += f" (one of {', '.join(map(str, a.choices))})"
            if a.default not in (None, False, argparse.SUPPRESS) and a.option_strings:
                h += f" (default `{a.default}`)"
            rows.append(f"| `{flag}` | {h} |")
        if rows:
            lines += ["| argument | meaning |", "|---|---|", *rows, ""]
    return "\n".join(lines) + "\n"


def method_chain() -> str:
    """The method as it runs (recon_core.method.CHAIN), as a table."""
    from recon_core.method import CHAIN

    from recon_core.config import Config, _get

    cfg = Config()
    lines = ["| # | step | the paper's? | by default | what it does | switched off by | stands aside by "
             "itself when |", "|---|---|---|---|---|---|---|"]
    for k, s in enumerate(CHAIN, 1):
        off = f"`{s.switch} = {_value(s.off)}`" if s.switch else ("always on" if not s.paper else "")
        on = "on" if s.paper or not s.switch or _get(cfg, s.switch) != s.off else "**off**"
        lines.append(f"| {k} | {s.name} | {'yes' if s.paper else 'no'} | {on} | {s.what} (`{s.module}`) | "
                     f"{off} | {s.stands_aside} |")
    return "\n".join(lines) + "\n"


def module_constants() -> list[tuple[str, str, str, str]]:
    """Every module-level numeric constant of the library outside the synthetic generator
    (module, name, value, comment): values fixed in the code rather than in the configuration,
    each with the comment that says what it is and why it is fixed (its line's, the comment lines
    above it, or those that continue it below)."""
    import ast
    from pathlib import Path

    root = Path(__file__).resolve().parent
    out = []
    for path in sorted(root.rglob("*.py")):
        if "synthetic" in path.relative_to(root).parts:
            continue
        src = path.read_text().splitlines()
        for node in ast.parse("\n".join(src)).body:
            if not (isinstance(node, ast.Assign) and len(node.targets) == 1
                    and isinstance(node.targets[0], ast.Name)):
                continue
            name, v = node.targets[0].id, node.value
            if not (name.isupper() and not name.startswith("_") and isinstance(v, ast.Constant)
                    and isinstance(v.value, (int, float)) and not isinstance(v.value, bool)):
                continue
            i = node.lineno - 1
            line = src[i]
            comment = line.split("#", 1)[1].strip() if "#" in line else ""
            if comment:                    # continued on the lines below, aligned comments
                j = i + 1
                while j < len(src) and src[j].strip().startswith("#") and not src[j].startswith("#"):
                    comment += " " + src[j].strip().lstrip("#").strip()
                    j += 1
            else:                          # or the comment block just above
                above, j = [], i - 1
                while j >= 0 and src[j].startswith("#"):
                    above.insert(0, src[j].lstrip("#").strip())
                    j -= 1
                comment = " ".join(above)
            module = ".".join(path.relative_to(root.parent).with_suffix("").parts)
            out.append((module, name, line.split("=", 1)[1].split("#", 1)[0].strip(), comment))
    return out


def constants_reference() -> str:
    """`module_constants` as a table."""
    lines = ["| module | constant | value | what it is, why it is fixed |", "|---|---|---|---|"]
    for module, name, value, comment in module_constants():
        lines.append(f"| `{module}` | `{name}` | `{value}` | {comment.replace('|', '/')} |")
    return "\n".join(lines) + "\n"


# -- the generated blocks of the docs pages -----------------------------------------------------
GENERATED = {"configuration": config_reference, "cli": cli_reference, "chain": method_chain,
             "constants": constants_reference}


def refresh(markdown: str) -> str:
    """The page with every generated block made anew: what lies between `<!-- generated: KEY -->`
    and `<!-- end generated: KEY -->` (the end marker added when missing)."""
    import re

    for key, make in GENERATED.items():
        start, end = f"<!-- generated: {key} -->", f"<!-- end generated: {key} -->"
        if start not in markdown:
            continue
        block = f"{start}\n{make().rstrip()}\n{end}"
        pattern = re.escape(start) + r"(.*?)" + re.escape(end) if end in markdown else re.escape(start)
        markdown = re.sub(pattern, lambda m: block, markdown, count=1, flags=re.S)
    return markdown


def main(argv=None) -> int:
    """`python -m recon_core.docs_reference [--check]`: write the docs pages' generated blocks
    (docs/cli.md, configuration.md, method.md) from the code, or with --check list the pages
    that are stale (exit 1)."""
    import argparse
    from pathlib import Path

    ap = argparse.ArgumentParser(description=(main.__doc__ or "").splitlines()[0])
    ap.add_argument("--check", action="store_true")
    ap.add_argument("--docs", type=Path, default=Path(__file__).resolve().parents[1] / "docs")
    args = ap.parse_args(argv)
    stale = []
    for page in sorted(args.docs.glob("*.md")):
        text = page.read_text()
        new = refresh(text)
        if new != text:
            stale.append(page)
            if not args.check:
                page.write_text(new)
    for page in stale:
        print(f"{page}: {'stale' if args.check else 'written'}")
    return 1 if (args.check and stale) else 0


if __name__ == "__main__":
    raise SystemExit(main())
