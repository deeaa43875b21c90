"""The driver's burst plan (LED order, per-LED exposure and level) and reconnect back-off."""

import math

import pytest

from fingerps_driver.board.backoff import Backoff
from fingerps_driver.capture.burst_plan import (
    BurstPlan,
    check_exposures,
    check_led_order,
    check_levels,
    make_plan,
)


def test_default_plan_is_every_led_in_order_with_the_common_values():
    plan = make_plan(led_count=7, led_order=range(7), exposure_time=0.01, led_level=0.5)
    assert plan == BurstPlan(tuple(range(7)), (0.01,) * 7, (0.5,) * 7)


def test_per_led_values_are_indexed_by_led_not_by_capture_position():
    plan = make_plan(led_count=4, led_order=[3, 0, 2], exposure_time=0.01,
                     exposure_times=[0.001, 0.002, 0.003, 0.004], led_level=1.0,
                     led_levels=[0.1, 0.2, 0.3, 0.4])
    assert plan.led_order == (3, 0, 2)
    assert plan.exposures_s == (0.004, 0.001, 0.003)
    assert plan.levels == (0.4, 0.1, 0.3)
    # empty lists mean "the common value"
    plan = make_plan(led_count=4, led_order=[1], exposure_time=0.02, exposure_times=[],
                     led_level=0.7, led_levels=[])
    assert plan == BurstPlan((1,), (0.02,), (0.7,))


@pytest.mark.parametrize(("order", "words"), [
    ([], "empty"),
    ([0, 7], "beyond"),
    ([-1], "beyond"),
    ([1, 2, 1], "more than once"),
])
def test_bad_led_orders_are_refused_with_a_reason(order, words):
    reason = check_led_order(order, 7)
    assert reason and words in reason
    with pytest.raises(ValueError, match="led_order"):
        make_plan(led_count=7, led_order=order, exposure_time=0.01, led_level=1.0)


def test_a_permutation_of_a_subset_is_fine():
    assert check_led_order([6, 0, 3], 7) is None


@pytest.mark.parametrize(("values", "words"), [
    ([0.01] * 6, "6 entries for 7"),
    ([0.01] * 6 + [0.0], "seconds"),
    ([0.01] * 6 + [2.0], "seconds"),
    ([0.01] * 6 + [math.nan], "seconds"),
])
def test_bad_exposure_lists_are_refused(values, words):
    reason = check_exposures(values, 7)
    assert reason and words in reason
    with pytest.raises(ValueError, match="exposure_times"):
        make_plan(led_count=7, led_order=range(7), exposure_time=0.01, exposure_times=values,
                  led_level=1.0)


@pytest.mark.parametrize(("values", "words"), [
    ([1.0] * 8, "8 entries"),
    ([1.0] * 6 + [1.5], "0..1"),
    ([1.0] * 6 + [-0.1], "0..1"),
])
def test_bad_level_lists_are_refused(values, words):
    reason = check_levels(values, 7)
    assert reason and words in reason
    assert check_levels(None, 7) is None and check_levels([], 7) is None


def test_common_values_out_of_range_are_refused():
    with pytest.raises(ValueError, match="exposure_time"):
        make_plan(led_count=3, led_order=[0], exposure_time=0.0, led_level=1.0)
    with pytest.raises(ValueError, match="led_level"):
        make_plan(led_count=3, led_order=[0], exposure_time=0.01, led_level=2.0)


def test_backoff_doubles_up_to_the_cap():
    backoff = Backoff(0.1, 1.0)
    assert [backoff.delay_s(i) for i in range(6)] == pytest.approx([0.1, 0.2, 0.4, 0.8, 1.0,
                                                                    1.0])
    assert backoff.delay_s(10**9) == 1.0  # no overflow after days away
    assert Backoff(0.5, 0.5).delay_s(3) == 0.5
    assert Backoff(0.2, 5.0, factor=1.0).delay_s(50) == 0.2


@pytest.mark.parametrize("args", [(0.0, 1.0), (1.0, 0.5), (0.1, 1.0, 0.5), (math.inf, 1.0)])
def test_backoff_refuses_bad_settings(args):
    with pytest.raises(ValueError):
        Backoff(*args)
    with pytest.raises(ValueError):
        Backoff().delay_s(-1)
