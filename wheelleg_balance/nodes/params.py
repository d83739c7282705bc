"""
ROS parameters from a typed configuration (core/schema.py): declare, describe, validate.

Each ``ParamSpec`` becomes one declared parameter with a descriptor that carries its
description, range and read-only flag, so ``ros2 param describe`` shows them and rclpy refuses
an out-of-range or read-only change before the node sees it. ``ParameterGuard`` is the
``add_on_set_parameters_callback`` of a node: it checks a set of changes against the whole
configuration (the cross-field rules too) and keeps the accepted configuration, so a bad value
is refused with a reason and nothing changes.
"""
from typing import Any, Callable, Dict, List, Optional, Tuple

from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType, SetParametersResult)
from rclpy.exceptions import ParameterUninitializedException
from rclpy.parameter import Parameter

from ..core.config import loosening
from ..core.schema import check, from_flat, ParamSpec, specs, with_changes

_ARRAY_TYPES = {float: ParameterType.PARAMETER_DOUBLE_ARRAY,
                int: ParameterType.PARAMETER_INTEGER_ARRAY,
                str: ParameterType.PARAMETER_STRING_ARRAY,
                bool: ParameterType.PARAMETER_BOOL_ARRAY}
_SCALAR_TYPES = {float: ParameterType.PARAMETER_DOUBLE, int: ParameterType.PARAMETER_INTEGER,
                 str: ParameterType.PARAMETER_STRING, bool: ParameterType.PARAMETER_BOOL}


def descriptor(spec: ParamSpec) -> ParameterDescriptor:
    """Build the descriptor rclpy checks (type, range, read-only); `ros2 param describe`."""
    kind = _ARRAY_TYPES[spec.item] if spec.kind is list else _SCALAR_TYPES[spec.kind]
    text = spec.description
    if spec.choices:
        text += ' (one of: %s)' % ', '.join(spec.choices)
    d = ParameterDescriptor(description=text, read_only=spec.read_only, type=kind)
    if spec.lo is None or spec.kind is list:
        return d  # list ranges are checked by ParamSpec.check, rclpy checks only scalars
    if spec.kind is int:
        d.integer_range = [IntegerRange(from_value=int(spec.lo), to_value=int(spec.hi),
                                        step=spec.step)]
    elif spec.kind is float:
        d.floating_point_range = [FloatingPointRange(from_value=float(spec.lo),
                                                     to_value=float(spec.hi))]
    return d


def declare(node, config_cls: type) -> Dict[str, Any]:
    """Declare every parameter of ``config_cls`` on ``node``; return {name: value}."""
    values = {}
    for spec in specs(config_cls):
        if spec.default is None or (spec.kind is list and not spec.default):
            # Unset, or an empty array whose type rclpy cannot infer: declare by type.
            node.declare_parameter(spec.name, Parameter.Type(descriptor(spec).type),
                                   descriptor(spec))
        else:
            node.declare_parameter(spec.name, spec.default, descriptor(spec))
        try:
            value = node.get_parameter(spec.name).value
        except ParameterUninitializedException:
            value = [] if spec.kind is list else None
        values[spec.name] = list(value) if isinstance(value, (list, tuple)) else value
    return values


def load(node, config_cls: type):
    """
    Declare the parameters and build the configuration; raise ValueError with every problem.

    What a config file or a --ros-args override sets is checked against the schema and the
    cross-field rules here, so a wrong file stops the node at start with a clear message.
    """
    values = declare(node, config_cls)
    cfg = from_flat(config_cls, values)
    problems = check(cfg)
    if problems:
        raise ValueError('invalid parameters: ' + '; '.join(problems))
    return cfg


class ParameterGuard:
    """
    The node's set-parameters callback over a configuration.

    ``on_change(changes, new_config)`` is called for an accepted set of changes (the node
    forwards them to its control loop); ``config`` is the accepted configuration.
    ``tighten_only()``: True while the robot balances; then a change that loosens a safety
    parameter (core/config.py TIGHTEN_ONLY) is refused.
    """

    def __init__(self, config, on_change: Callable[[Dict[str, Any], Any], None],
                 tighten_only: Callable[[], bool] = lambda: False):
        self.config = config
        self._on_change = on_change
        self._tighten_only = tighten_only

    def __call__(self, parameters: List[Parameter]) -> SetParametersResult:
        """Check ``parameters`` together; accept all of them or none."""
        ok, reason, new = self.check({p.name: p.value for p in parameters})
        if not ok:
            return SetParametersResult(successful=False, reason=reason)
        changes = {p.name: _plain(p.value) for p in parameters}
        self.config = new
        self._on_change(changes, new)
        return SetParametersResult(successful=True)

    def check(self, changes: Dict[str, Any]) -> Tuple[bool, str, Optional[Any]]:
        """Return (ok, reason, the configuration with the changes)."""
        try:
            new = with_changes(self.config, {k: _plain(v) for k, v in changes.items()})
        except ValueError as exc:
            return False, str(exc), None
        problems = check(new)
        if not problems and self._tighten_only():
            problems = loosening(self.config, {k: _plain(v) for k, v in changes.items()})
        if problems:
            return False, '; '.join(problems), None
        return True, '', new


def _plain(value: Any) -> Any:
    # rclpy hands arrays over as array.array or numpy arrays: make them lists.
    if isinstance(value, (str, bytes)) or not hasattr(value, '__len__'):
        return value
    return list(value)
