"""The method's chain (recon_core.method.CHAIN) is the configuration's: every switch exists,
`--method paper` switches off exactly the steps beyond the paper, and the paper's plain path
is a valid configuration."""

from __future__ import annotations

from recon_core.config import BEYOND_PAPER, METHODS, Config, _get, preset, schema, validate
from recon_core.method import CHAIN


def test_every_switch_is_a_parameter_and_its_off_value_is_valid():
    fields = schema()
    for s in CHAIN:
        if s.switch:
            assert s.switch in fields, s.name
            assert not s.paper, f"{s.name}: a step of the paper has no switch"
            validate(Config().with_overrides({s.switch: s.off}))


def test_the_paper_method_switches_off_every_step_beyond_it_and_nothing_else():
    beyond = {s.switch for s in CHAIN if not s.paper and s.switch}
    assert set(BEYOND_PAPER) == beyond == set(METHODS["paper"])
    cfg = preset("default", "paper")
    for s in CHAIN:
        if s.switch:
            assert _get(cfg, s.switch) == s.off


def test_steps_are_unique_and_their_modules_exist():
    import importlib

    names = [s.name for s in CHAIN]
    assert len(names) == len(set(names))
    for s in CHAIN:
        importlib.import_module(s.module)
