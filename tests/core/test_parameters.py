"""fingerps_ros.parameter_table and fingerps_ros.parameters.declare_parameters on nodes of
this process (``ros_node``'s context), without a graph: a table declared in its order with
its descriptors, callable defaults, and checks in force while declaring or after."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from rclpy.exceptions import InvalidParameterValueException
from rclpy.node import Node
from rclpy.parameter import Parameter

from fingerps_ros.parameter_table import ParameterRow, one_of
from fingerps_ros.parameters import declare_parameters

TABLE = (
    ParameterRow("count", 3, "How many", min_value=1, max_value=10, integer=True,
                 read_only=True),
    ParameterRow("order", lambda: [], "In which order", dynamic_typing=True),
    ParameterRow("gain", 0.5, "How much", min_value=0.0, max_value=1.0),
    ParameterRow("mode", "a", "Which mode", constraints="a or b", check=one_of("a", "b")),
)


@pytest.fixture
def make_node(ros_node: Node) -> Iterator:
    made: list[Node] = []

    def make(**overrides: object) -> Node:
        made.append(Node("table_test", context=ros_node.context, parameter_overrides=[
            Parameter(name, value=value) for name, value in overrides.items()]))
        return made[-1]

    yield make
    for node in made:
        node.destroy_node()


def test_a_table_is_declared_in_order_with_its_descriptors(make_node) -> None:
    node = make_node()
    declare_parameters(node, TABLE)
    assert [n for n in node._parameters if n in {r.name for r in TABLE}] == [
        "count", "order", "gain", "mode"]
    count, order, gain, mode = node.describe_parameters(["count", "order", "gain", "mode"])
    assert count.read_only and count.description == "How many"
    assert [(r.from_value, r.to_value) for r in count.integer_range] == [(1, 10)]
    assert order.dynamic_typing and not count.dynamic_typing
    assert [(r.from_value, r.to_value) for r in gain.floating_point_range] == [(0.0, 1.0)]
    assert mode.additional_constraints == "a or b" and not mode.read_only


def test_a_callable_default_is_evaluated_at_declaration(make_node) -> None:
    node = make_node()
    rows = (TABLE[0], ParameterRow(
        "order", lambda: list(range(node.get_parameter("count").value)), "In which order"))
    declare_parameters(node, rows)
    assert list(node.get_parameter("order").value) == [0, 1, 2]
    assert TABLE[1].default_value() == []


def test_checks_refuse_bad_values_with_a_reason(make_node) -> None:
    node = make_node()
    checks = declare_parameters(node, TABLE)
    result = node.set_parameters([Parameter("mode", value="c")])[0]
    assert not result.successful and result.reason == "mode='c': must be one of a, b"
    assert node.set_parameters([Parameter("mode", value="b")])[0].successful
    assert checks.problems([Parameter("mode", value="z")]) == [
        "mode='z': must be one of a, b"]


def test_a_bad_start_value_stops_the_declaration_or_waits_for_the_caller(make_node) -> None:
    with pytest.raises(InvalidParameterValueException, match="must be one of a, b"):
        declare_parameters(make_node(mode="c"), TABLE)
    node = make_node(mode="c")
    checks = declare_parameters(node, TABLE, check_while_declaring=False)
    assert node.get_parameter("mode").value == "c"
    assert checks.problems([node.get_parameter("mode")]) == ["mode='c': must be one of a, b"]
    assert not node.set_parameters([Parameter("mode", value="d")])[0].successful
