"""Node parameters with descriptors: ranges, allowed values, and which ones can change at run time.

    SPEC = {'k': Param(5, 'candidates per query', dynamic=True, range=(1, 1000)), ...}
    values = declare_all(node, SPEC, on_change=node.apply_parameters)

Read-only parameters say so to `ros2 param set` ("Trying to set a read-only parameter"). Dynamic ones
are range-checked by rclpy from their FloatingPointRange / IntegerRange, checked for allowed values
and by `check` here, and rejected with a reason; accepted changes update `values` (the dict the node
reads) and then call on_change({name: value}).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult


@dataclass(frozen=True)
class Param:
    """One node parameter. range: inclusive (low, high) for int / float ones; choices: allowed
    strings; check: value -> '' when fine, else the reason it is refused."""

    default: Any
    description: str
    dynamic: bool = False
    range: tuple | None = None
    choices: tuple = ()
    check: Callable[[Any], str] | None = None

    def descriptor(self) -> ParameterDescriptor:
        d = ParameterDescriptor(description=self.description, read_only=not self.dynamic)
        if self.range is not None and isinstance(self.default, bool):
            raise TypeError('a bool parameter has no range')
        if self.range is not None and isinstance(self.default, int):
            d.integer_range = [IntegerRange(from_value=int(self.range[0]), to_value=int(self.range[1]), step=1)]
        elif self.range is not None:
            d.floating_point_range = [
                FloatingPointRange(from_value=float(self.range[0]), to_value=float(self.range[1]), step=0.0)
            ]
        notes = []
        if self.choices:
            notes.append('one of: ' + ' | '.join(self.choices))
        notes.append('settable at run time' if self.dynamic else 'read at start (read-only)')
        d.additional_constraints = '; '.join(notes)
        return d

    def problem(self, value) -> str:
        if self.choices and value not in self.choices:
            return f'must be one of {" | ".join(self.choices)}, got {value!r}'
        return self.check(value) if self.check else ''


def declare_all(node, spec: dict[str, Param | tuple], on_change: Callable[[dict], None] | None = None) -> dict:
    """Declare every parameter of `spec`; return {name: value} (kept current on run-time changes).
    A start value outside its range or choices raises ValueError naming the parameter."""
    from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException

    # a plain (default, description) pair is a read-only Param (the format before descriptors)
    spec = {name: p if isinstance(p, Param) else Param(*p) for name, p in spec.items()}
    values = {}
    for name, param in spec.items():
        try:
            node.declare_parameter(name, param.default, param.descriptor())
        except (InvalidParameterValueException, InvalidParameterTypeException) as e:
            # rclpy: "Invalid parameter value (-1) for parameter. Reason: <why>: <name>" -> <why>
            reason = str(e).split('Reason: ', 1)[-1]
            reason = reason[: -len(f': {name}')] if reason.endswith(f': {name}') else reason
            raise ValueError(f'parameter {name}: {reason}') from None
        values[name] = node.get_parameter(name).value
        problem = param.problem(values[name])
        if problem:
            raise ValueError(f'parameter {name} {problem}')

    def on_set(parameters) -> SetParametersResult:
        changes = {}
        for p in parameters:
            param = spec.get(p.name)
            if param is None:  # another module's parameter (use_sim_time, ...): not ours to judge
                continue
            problem = param.problem(p.value)
            if problem:
                return SetParametersResult(successful=False, reason=f'{p.name} {problem}')
            changes[p.name] = p.value
        if changes:
            # rclpy calls this before it stores the values: apply here, so a refused on_change
            # (ValueError) leaves both the node and the parameter server unchanged
            old = {k: values[k] for k in changes}
            values.update(changes)
            try:
                if on_change is not None:
                    on_change(changes)
            except ValueError as e:
                values.update(old)
                return SetParametersResult(successful=False, reason=str(e))
            except Exception as e:  # noqa: BLE001  a fault applying it: refused, the node goes on
                values.update(old)
                health = getattr(node, 'health', None)
                if health is not None:
                    health.problem('internal_error', f'applying {sorted(changes)}: {type(e).__name__}: {e}')
                return SetParametersResult(successful=False, reason=f'internal error: {type(e).__name__}: {e}')
            node.get_logger().info('parameters changed: ' + ', '.join(f'{k}={v!r}' for k, v in changes.items()))
        return SetParametersResult(successful=True)

    node.add_on_set_parameters_callback(on_set)
    return values


# Lower bound of every period / rate parameter: a /diagnostics period of 1e-6 s once took a core and
# sent 1,600 messages a second (issue 25). 0 still means off.
MIN_PERIOD_S = 0.05


def period_problem(value) -> str:
    """Param.check of a period in seconds: 0 (off) or at least MIN_PERIOD_S."""
    return (
        '' if value == 0 or value >= MIN_PERIOD_S else f'must be 0 (off) or at least {MIN_PERIOD_S:g} s, got {value!r}'
    )


def diagnostics_period(default: float = 1.0) -> Param:
    """The diagnostics_period parameter every node declares (one definition, one lower bound)."""
    return Param(
        default,
        f'seconds between /diagnostics messages; 0 = off, else at least {MIN_PERIOD_S:g}',
        dynamic=True,
        range=(0.0, 3600.0),
        check=period_problem,
    )
