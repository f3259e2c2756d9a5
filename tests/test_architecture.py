"""The structure docs/architecture.md describes: the core never imports the viewer, no module
outside the synthetic package imports it, the method packages talk only through the shared
layers, and no two modules of the library import each other."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
METHOD = ("sparse", "dense", "euclidean")


def _imports(path: Path) -> set[str]:
    """Every module a file imports (absolute names; relative ones resolved)."""
    tree = ast.parse(path.read_text())
    pkg = ".".join(path.relative_to(ROOT).with_suffix("").parts[:-1])
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = pkg.split(".")[: len(pkg.split(".")) - node.level + 1]
                base = ".".join(parent + ([base] if base else []))
            out.add(base)
            out.update(f"{base}.{a.name}" for a in node.names)
    return out


def test_importing_the_pipeline_loads_no_generator_and_no_viewer():
    code = ("import sys, recon_core.pipeline, recon_core.cli; "
            "bad = sorted(m for m in sys.modules if m.startswith(('recon_core.synthetic', "
            "'aerec_viewer', 'numba', 'viser'))); print(bad); sys.exit(1 if bad else 0)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stdout + r.stderr


def test_method_packages_import_only_shared_layers():
    """sparse, dense and euclidean never import each other (only geometry, model, io, config,
    events, errors, context); no core module imports the viewer or the generator."""
    for path in (ROOT / "recon_core").rglob("*.py"):
        rel = path.relative_to(ROOT / "recon_core").parts
        mods = _imports(path)
        assert not any(m.startswith("aerec_viewer") for m in mods), path
        if rel[0] == "synthetic":
            continue                    # the generator itself and the truth-based checks
        assert not any(m.startswith("recon_core.synthetic") for m in mods), path
        if rel[0] in METHOD:
            others = [m for m in mods for o in METHOD if o != rel[0] and m.startswith(f"recon_core.{o}")]
            assert not others, f"{path} imports {others}"


def test_the_bend_package_sits_between_the_shared_layers_and_the_stages():
    """recon_core.bend (the pushbroom model and the corrections it makes possible) is used by the
    stages and uses none of them: only geometry, model and the run's shared modules."""
    allowed = ("recon_core.bend", "recon_core.geometry", "recon_core.model", "recon_core.config",
               "recon_core.errors", "recon_core.events")
    for path in (ROOT / "recon_core" / "bend").rglob("*.py"):
        bad = [m for m in _imports(path) if m.startswith("recon_core") and m != "recon_core"
               and not m.startswith(allowed)]
        assert not bad, f"{path} imports {bad}"


def test_synth_command_presets_match_the_generator():
    from recon_core.synthetic.cli import PRESET_NAMES
    from recon_core.synthetic.generator import PRESETS

    assert set(PRESET_NAMES) == set(PRESETS)


def test_no_import_cycle_in_the_library():
    """Module-level and function-level imports alike: a cycle is a layer that does not hold."""
    mods = {".".join(p.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__"): p
            for p in (ROOT / "recon_core").rglob("*.py")}
    graph = {m: {d for d in _imports(p) if d in mods and d != m} for m, p in mods.items()}
    state: dict[str, int] = {}

    def visit(m, stack):
        state[m] = 1
        for d in graph[m]:
            if state.get(d) == 1:
                raise AssertionError("import cycle: " + " -> ".join(stack[stack.index(d):] + [d]))
            if d not in state:
                visit(d, stack + [d])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])


def test_no_function_of_the_library_is_longer_than_80_lines():
    """A function mixing several concerns is where the next change goes wrong: each of
    recon_core's (the synthetic generator aside) fits in 80 lines, its docstring included."""
    import ast
    from pathlib import Path

    root = Path(__file__).resolve().parents[1] / "recon_core"
    long = []
    for p in sorted(root.rglob("*.py")):
        if "synthetic" in p.relative_to(root).parts:
            continue
        for n in ast.walk(ast.parse(p.read_text())):
            if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)) and n.end_lineno - n.lineno + 1 > 80:
                long.append(f"{p.relative_to(root.parent)}:{n.lineno} {n.name} ({n.end_lineno - n.lineno + 1} lines)")
    assert not long, long
