"""lln_ros.nodes.parameters on an in-process rclpy node: descriptors, run-time validation, rollback."""

import pytest
import rclpy
from rclpy.context import Context
from rclpy.parameter import Parameter

from lln_ros.nodes.parameters import Param, declare_all


@pytest.fixture
def node():
    context = Context()
    rclpy.init(context=context, domain_id=99)
    n = rclpy.create_node('param_test', context=context, start_parameter_services=False)
    yield n
    n.destroy_node()
    rclpy.try_shutdown(context=context)


def test_descriptors_validation_and_rollback(node):
    applied = []

    def on_change(changes):
        if changes.get('k') == 13:
            raise ValueError('k 13 is unlucky')
        applied.append(changes)

    values = declare_all(
        node,
        {
            'k': Param(5, 'candidates', dynamic=True, range=(1, 100)),
            'gain': Param(0.5, 'a gain', dynamic=True, range=(0.0, 1.0)),
            'mode': Param('a', 'the mode', choices=('a', 'b')),
            'method': Param('x', 'the method', dynamic=True, choices=('x', 'y')),
            'legacy': (7, 'declared in the old (default, description) form'),
        },
        on_change,
    )
    d = node.describe_parameter('k')
    assert not d.read_only and d.integer_range[0].to_value == 100 and 'run time' in d.additional_constraints
    assert node.describe_parameter('mode').read_only and node.describe_parameter('legacy').read_only
    assert node.describe_parameter('gain').floating_point_range[0].to_value == 1.0
    assert node.set_parameters([Parameter('k', value=7)])[0].successful and values['k'] == 7
    assert applied == [{'k': 7}]
    for name, value, reason in (
        ('k', 0, 'out of range'),
        ('gain', 1.5, 'out of range'),
        ('method', 'z', 'must be one of x | y'),
        ('mode', 'b', 'read-only'),
        ('legacy', 8, 'read-only'),
        ('k', 13, 'unlucky'),
    ):
        result = node.set_parameters([Parameter(name, value=value)])[0]
        assert not result.successful and reason in result.reason, (name, result.reason)
    assert values['k'] == 7 and node.get_parameter('k').value == 7  # the refused 13 changed nothing
    assert values['method'] == 'x'


def test_start_values_outside_the_range_are_refused(node):
    with pytest.raises(ValueError, match='parameter n .*must be one of'):
        declare_all(node, {'n': Param('c', 'n', choices=('a', 'b'))})
