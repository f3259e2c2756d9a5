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
    (its steps that are CHAIN's, in CHAIN's order), and the sparse closing plan, whose steps
    first appear in CHAIN's order (the tied adjustment: `tie`; the bend step: `bend_step`; the
    adjustment with the correction refitted: `within_tile`)."""
    from recon_core.bend.closing import closing_plan
    from recon_core.euclidean.upgrade_stage import UPGRADE_CHAIN

    order = [s.name for s in CHAIN]
    ran = [name for name, _ in UPGRADE_CHAIN if name in order]
    assert ran == [n for n in order if n in ran]
    assert {"upgrade", "metric_bend", "gcp_bend", "dem_bend"} <= set(ran)

    def chain_names(plan):
        names = []
        for s in plan:
            name = {"bend": "bend_step"}.get(s.name) or ("within_tile" if s.correct else "tie")
            if s.name != "filter" and name not in names:
                names.append(name)
        return names

    first = chain_names(closing_plan(2, bend=True))
    assert first == [n for n in order if n in first] == ["tie", "bend_step", "within_tile"]
    assert chain_names(closing_plan(2, bend=False)) == ["tie", "within_tile"]
    plan = [s.name for s in closing_plan(2, bend=True)]
    assert plan == ["filter", "adjust", "filter", "bend", "adjust", "filter", "bend", "adjust", "bend"]
    steps = closing_plan(2, bend=True)
    assert [s.correct for s in steps if s.name == "adjust"] == [False, True, True]
    assert [s.converge for s in steps if s.name == "adjust"] == [False, False, True]
    assert all(s.converge and not s.correct for s in closing_plan(0, bend=True) if s.name == "adjust")
