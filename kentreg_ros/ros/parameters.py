"""The node's parameters through rclpy: declared from :data:`kentreg_ros.io.params.PARAMETERS`,
validated by the configuration's own rules, changed at run time with a reason on rejection.

Numbers are read as a user writes them: an integer for a floating-point parameter (``max_range:
100``, ``-p max_range:=100``, ``ros2 param set ... max_range 100``) is accepted, since the value
is checked and converted by :func:`~kentreg_ros.io.params.apply_parameters`, the same function
the command lines use; the floating-point parameters are declared with dynamic typing for that.
A value refused is a :class:`~kentreg_ros.io.errors.ParameterError` naming the parameters and
the reason (:class:`StartupError` at startup), which the node hands to ``ros2 param set`` or logs
before it exits. Names that are not the node's (a shared bringup file under ``/**`` holds other
nodes' keys; research fields such as ``em.tolerance``) are warned about once and ignored.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.exceptions import (
    InvalidParameterTypeException,
    InvalidParameterValueException,
    ParameterException,
)
from rclpy.node import Node
from rclpy.parameter import Parameter as RosParameter
from rclpy.time_source import USE_SIM_TIME_NAME
from rclpy.type_description_service import START_TYPE_DESCRIPTION_SERVICE_PARAM

from kentreg_ros.core import KentRegConfig
from kentreg_ros.io.errors import ParameterError
from kentreg_ros.io.params import (
    PARAMETERS,
    NodeSettings,
    Parameter,
    Settings,
    apply_parameters,
    product_values,
)

#: Parameters every rclpy node has besides its own (rclpy declares and reads them itself):
#: the clock source, whether to serve ~/get_type_description, and QoS overrides of publishers
#: and subscriptions (``qos_overrides.<topic>.<publisher|subscription>.<policy>``).
RCLPY_PARAMETERS = frozenset({USE_SIM_TIME_NAME, START_TYPE_DESCRIPTION_SERVICE_PARAM})
QOS_OVERRIDES_PREFIX = 'qos_overrides.'
_BY_NAME = {p.name: p for p in PARAMETERS}


class StartupError(ParameterError):
    """The node cannot start with the given parameters (message says which and why; ``names``
    which, where it can tell).

    Part of the library's error hierarchy (like the command lines' ``CliError``), so callers
    that construct the node catch it with ``except KentRegError``.
    """


def descriptor(p: Parameter) -> ParameterDescriptor:
    """The ROS descriptor of a parameter: its description, range or choices, read-only flag;
    floating-point parameters take integers too (dynamic typing, see the module docstring)."""
    desc = ParameterDescriptor(
        name=p.name,
        description=p.description,
        read_only=p.read_only,
        dynamic_typing=isinstance(p.default, float),
    )
    if p.choices:
        desc.additional_constraints = 'one of: ' + ', '.join(map(str, p.choices))
    if p.range is not None and isinstance(p.default, int) and not isinstance(p.default, bool):
        desc.integer_range = [
            IntegerRange(from_value=int(p.range[0]), to_value=int(p.range[1]), step=1)
        ]
    elif p.range is not None and isinstance(p.default, float):
        desc.floating_point_range = [
            FloatingPointRange(from_value=float(p.range[0]), to_value=float(p.range[1]), step=0.0)
        ]
    return desc


def not_ours(names: Iterable[str]) -> list[str]:
    """The names among ``names`` that are neither the node's nor rclpy's own."""
    return sorted(
        n
        for n in names
        if n not in _BY_NAME
        and n not in RCLPY_PARAMETERS
        and not n.startswith(QOS_OVERRIDES_PREFIX)
    )


def declare(node: Node) -> Settings:
    """Read what the node was given (files, ``-p``, overrides), validate it, and declare every
    parameter with its descriptor and its validated value.

    ``node`` must be made with ``automatically_declare_parameters_from_overrides=True``, so
    that every name given is visible through the public parameter API.

    Raises
    ------
    StartupError
        A value of the wrong type, out of range, not among its choices, or inconsistent with
        another.
    """
    given: dict[str, Any] = dict(node.get_parameters_by_prefix(''))  # name -> Parameter
    values = {name: p.value for name, p in given.items() if name in _BY_NAME}
    try:
        settings = apply_parameters(values, research=False, strict=False)
    except ParameterError as exc:
        raise StartupError(exc.reason, names=exc.names) from exc
    unknown = not_ours(given)
    for name in values:
        node.undeclare_parameter(name)
    current = product_values(settings.config, settings.node)
    declarations = [(p.name, current[p.name], descriptor(p)) for p in PARAMETERS]
    try:
        # rclpy annotates `parameters` as an invariant List of a Union of tuples.
        node.declare_parameters('', declarations, ignore_override=True)  # type: ignore[arg-type]
    except (
        InvalidParameterTypeException,
        InvalidParameterValueException,
        ParameterException,
    ) as exc:
        raise StartupError(str(exc)) from exc
    return Settings(settings.config, settings.node, tuple(unknown))


def changes(params: Iterable[RosParameter], config: KentRegConfig, node: NodeSettings) -> Settings:
    """The settings after a run-time change of ``params`` (names that are not the node's,
    such as rclpy's ``use_sim_time``, are left to rclpy).

    Raises
    ------
    ParameterError
        The change is refused: a read-only parameter, a bad value or a broken rule; ``str()``
        is the reason ``ros2 param set`` shows.
    """
    updates: dict[str, Any] = {}
    for p in params:
        spec = _BY_NAME.get(p.name)
        if spec is None:
            continue  # rclpy's own (use_sim_time, ...)
        if spec.read_only:
            raise ParameterError(f'{p.name} takes effect only at startup', names=(p.name,))
        updates[p.name] = p.value
    return apply_parameters(updates, config=config, node=node, research=False)


def values_text(params: Mapping[str, Any] | Iterable[RosParameter]) -> str:
    """``name=value, ...`` for a log line."""
    items = params.items() if isinstance(params, Mapping) else ((p.name, p.value) for p in params)
    return ', '.join(f'{name}={value!r}' for name, value in items)
