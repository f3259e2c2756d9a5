"""Every configuration field, generated from the schema (recon_core.config.schema): a wrong type,
NaN and an out-of-range value are each refused before any compute, in one line naming the TOML
file and the field, exit 2, nothing written. A new field is tested the day it is added."""

from __future__ import annotations

import math

import pytest

from recon_core.cli import main
from recon_core.config import Config, Rule, schema, validate

FIELDS = schema()


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v + '"'
    if isinstance(v, float) and math.isnan(v):
        return "nan"
    if isinstance(v, (tuple, list)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return repr(v)


def _toml(name: str, value) -> str:
    sec, _, fld = name.rpartition(".")
    line = f"{fld} = {_toml_value(value)}\n"
    return line if not sec else f"[{sec}]\n{line}"


def _bad_values(name: str, ann: str, rule: Rule) -> list[tuple[str, object]]:
    """(kind, value) cases a field must refuse."""
    kinds = [a.strip() for a in ann.split("|")]
    default = getattr(getattr(Config(), name.split(".")[0]), name.split(".")[1]) if "." in name \
        else getattr(Config(), name)
    out = []
    if "bool" in kinds:
        out.append(("type", 3))
    elif "str" in kinds:
        out.append(("type", 5))
    elif any(k.startswith("tuple") for k in kinds):
        out.append(("type", ["a", "b"]))
    else:
        out.append(("type", "x"))
    numeric = [k for k in kinds if k in ("int", "float") or k.startswith("tuple")]
    if numeric and "float" in " ".join(kinds) + ("tuple" if kinds[0].startswith("tuple") else ""):
        nan = float("nan")
        out.append(("nan", (nan, nan) if kinds[0].startswith("tuple") else nan))
    if rule.choices is not None:
        out.append(("range", "no-such-choice" if isinstance(default, str) else 99))
    elif rule.lo is not None or rule.hi is not None:
        isint = "int" in kinds and "float" not in kinds
        if rule.lo is not None:
            v = rule.lo if rule.lo_open else rule.lo - (1 if isint else max(abs(rule.lo) * 0.5, 0.5))
        else:
            v = rule.hi + 1
        v = int(v) if isint else float(v)
        out.append(("range", (v, v) if kinds[0].startswith("tuple") else v))
    return out


CASES = [(name, kind, value) for name, (ann, rule) in FIELDS.items()
         for kind, value in _bad_values(name, ann, rule)]


def test_every_field_has_a_rule_or_is_free_by_nature():
    """A number without a range is a field the schema forgot (booleans and free text need none)."""
    for name, (ann, rule) in FIELDS.items():
        free = ann.split("|")[0].strip() in ("bool", "str") or name == "dense.scheduler"
        assert free or rule != Rule(), f"{name}: give it a Rule (range or choices) in recon_core/config.py"


@pytest.mark.parametrize("name, kind, value", CASES, ids=[f"{n}-{k}" for n, k, _ in CASES])
def test_a_bad_value_is_refused_before_any_compute(name, kind, value, small_site, tmp_path, capsys):
    f = tmp_path / "c.toml"
    f.write_text(_toml(name, value))
    out = tmp_path / "o"
    assert main(["run", str(small_site), "--out", str(out), "--config", str(f), "--quiet"]) == 2, name
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"aerec: error: {f}:") and name in err[0], err
    assert not out.exists()


def test_the_defaults_and_the_paper_method_pass():
    from recon_core.config import METHODS, PRESETS, preset

    for p in PRESETS:
        for m in METHODS:
            validate(preset(p, m))


@pytest.mark.parametrize("body, words", [
    ("[sgbm]\np1 = 40\np2 = 10\n", "P2 must be >= P1"),
    ("[features]\nstretch_percentiles = [99.0, 1.0]\n", "the lower first"),
    ("[tiling]\ntile_size = 256\n[dense]\nstep = 40\n", "at least 8 reference pixels"),
    ("[dense]\ncore_margin_px = 600\n", "less than half the tile size"),
    ("[tiling]\noverlap = 1000\n", "smaller than the tile size"),
    ("[dense]\nmax_two_view_spread = 0.5\n", "or at least 1"),
])
def test_relations_between_fields(body, words, small_site, tmp_path, capsys):
    f = tmp_path / "c.toml"
    f.write_text(body)
    assert main(["run", str(small_site), "--out", str(tmp_path / "o"), "--config", str(f), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("aerec: error:") == 1 and words in err, err


@pytest.mark.parametrize("make, words", [
    (lambda p: p.write_bytes(b"\x7fELF\x02\x01\x01\x00\xff\xfe" * 50), "not a text file"),
    (lambda p: p.mkdir(), "not a configuration file"),
    (lambda p: p.write_bytes(b"# x\n" * 400_000), "not a configuration file"),
])
def test_a_config_that_is_not_one(make, words, small_site, tmp_path, capsys):
    f = tmp_path / "c.toml"
    make(f)
    assert main(["run", str(small_site), "--out", str(tmp_path / "o"), "--config", str(f), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("aerec: error:") == 1 and words in err and "Traceback" not in err, err


def test_dev_zero_is_refused_without_reading_it(small_site, tmp_path, capsys):
    assert main(["run", str(small_site), "--out", str(tmp_path / "o"), "--config", "/dev/zero", "--quiet"]) == 2
    assert "not a configuration file" in capsys.readouterr().err


def test_the_choices_are_what_the_modules_implement():
    from recon_core.config import rule_of
    from recon_core.dense.matchers import MATCHERS
    from recon_core.euclidean.dsm import STATS
    from recon_core.sparse.bundle import LOSSES, SOLVERS

    for (sec, name), impl in {("bundle", "loss"): LOSSES, ("bundle", "solver"): SOLVERS,
                              ("dense", "matcher"): MATCHERS, ("dsm", "stat"): STATS}.items():
        assert set(rule_of(sec, name).choices) == set(impl), (sec, name)
