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


def test_the_stages_run_their_steps_in_the_chains_order():
    """The two places that run corrections in order follow CHAIN: the upgrade's UPGRADE_CHAIN
    (its steps that are CHAIN's, in CHAIN's order) and the sparse closing adjustments, whose
    plan's bend steps come after the first adjustment and start each correction round."""
    from recon_core.bend.closing import closing_plan
    from recon_core.euclidean.upgrade_stage import UPGRADE_CHAIN

    order = [s.name for s in CHAIN]
    ran = [name for name, _ in UPGRADE_CHAIN if name in order]
    assert ran == [n for n in order if n in ran]
    assert {"upgrade", "metric_bend", "gcp_bend", "dem_bend"} <= set(ran)
    plan = [s.name for s in closing_plan(2, bend=True)]
    assert plan == ["filter", "adjust", "filter", "bend", "adjust", "filter", "bend", "adjust", "bend"]
    steps = closing_plan(2, bend=True)
    assert [s.correct for s in steps if s.name == "adjust"] == [False, True, True]
    assert [s.converge for s in steps if s.name == "adjust"] == [False, False, True]
    assert "bend" not in [s.name for s in closing_plan(2, bend=False)]
    assert all(s.converge for s in closing_plan(0, bend=True) if s.name == "adjust")
