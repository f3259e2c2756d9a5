"""The view-update rate measured from camera messages, and the point budget that follows it."""

import numpy as np

from aerec_viewer.framerate import GESTURE_GAP_S, REST_S, BudgetGovernor, ViewRateMeter


def gesture(meter, client, t0, fps, n):
    ts = t0 + np.arange(n) / fps
    for t in ts:
        meter.moved(client, float(t))
    return float(ts[-1])


def test_a_gesture_is_measured_once_when_the_view_rests():
    m = ViewRateMeter()
    end = gesture(m, 1, 10.0, 4.0, 12)
    assert m.rate(end + 0.5 * REST_S) is None            # the hand still on the mouse
    assert abs(m.rate(end + REST_S + 0.01) - 4.0) < 1e-9
    assert m.rate(end + 2 * REST_S) is None              # said once


def test_short_gestures_and_pauses_say_nothing():
    m = ViewRateMeter()
    end = gesture(m, 1, 0.0, 20.0, 4)                    # a flick: too few moves
    assert m.rate(end + REST_S + 0.01) is None
    # moves separated by more than the gesture gap are not a gesture
    for k in range(10):
        m.moved(1, 100.0 + k * (GESTURE_GAP_S + 0.1))
    assert m.rate(100.0 + 10 * (GESTURE_GAP_S + 0.1) + REST_S) is None


def test_the_slowest_client_is_the_one_that_counts():
    m = ViewRateMeter()
    e1 = gesture(m, 1, 0.0, 30.0, 40)
    e2 = gesture(m, 2, 0.0, 5.0, 10)
    assert abs(m.rate(max(e1, e2) + REST_S + 0.01) - 5.0) < 1e-9


def test_governor_lowers_the_budget_until_the_target_then_hides_tiles():
    gov = BudgetGovernor(start=150_000)
    budget, steps = 150_000, []
    # frame time = 40 ms fixed + 1.5 us per point (software WebGL, measured order)
    for _ in range(20):
        fps = 1.0 / (0.040 + 1.5e-6 * budget)
        new = gov.observe(fps, budget)
        if new is None:
            break
        assert new < budget and new % 10_000 == 0
        budget = new
        steps.append(budget)
    fps = 1.0 / (0.040 + 1.5e-6 * budget)
    assert fps >= gov.TARGET_FPS and len(steps) <= 4 and not gov.hide_tiles
    # a scene whose fixed part alone is too slow: floor, then the outlines go
    gov = BudgetGovernor(start=150_000)
    budget = 150_000
    for _ in range(30):
        new = gov.observe(1.0 / (0.090 + 1.5e-6 * budget), budget)
        budget = budget if new is None else new
    assert budget == gov.MIN_BUDGET and gov.hide_tiles


def test_governor_gives_back_what_it_took_and_respects_the_operator():
    gov = BudgetGovernor(start=150_000)
    assert gov.observe(60.0, 150_000) is None            # never above where it started
    assert gov.observe(60.0, 40_000) == 60_000
    assert gov.observe(60.0, 120_000) == 150_000
    gov.user_set = True
    assert gov.observe(2.0, 150_000) is None
