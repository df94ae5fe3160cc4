"""YAML as ROS reads it: numbers written as a user writes them, and ``KEY=VALUE`` overrides.

The parameter files (:mod:`kentreg_ros.io.params`) and the command lines' ``--set`` read their
values here, so the node (through rcl) and the command lines read a file alike.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from typing import Any

import yaml

from kentreg_ros.core import ConfigError

__all__ = ['NumberLoader', 'load_yaml', 'parse_overrides']


class NumberLoader(yaml.SafeLoader):
    """PyYAML's safe loader reading numbers as a user writes them and as ROS reads them.

    PyYAML follows YAML 1.1, where a float needs a decimal point: ``1e-3``, ``1E-3`` and ``1e3``
    come back as strings, while rcl (which reads the node's parameter files) and YAML 1.2 read
    them as numbers. This loader adds YAML 1.2's float forms (an exponent with or without a
    point or sign), so the command lines and the node read a file alike.
    """


_FLOAT_12 = re.compile(r'^[-+]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)[eE][-+]?[0-9]+$')
for _first in '-+.0123456789':
    NumberLoader.add_implicit_resolver('tag:yaml.org,2002:float', _FLOAT_12, [_first])


def load_yaml(text: str) -> Any:
    """``text`` parsed by :class:`NumberLoader`."""
    return yaml.load(text, Loader=NumberLoader)  # noqa: S506 - a SafeLoader subclass


def parse_overrides(items: Iterable[str]) -> dict[str, Any]:
    """``KEY=VALUE`` items as ``{KEY: value}``, each value read as a YAML scalar.

    ``em.max_iterations=30`` gives the integer 30, ``refine.normal_weight=false`` the boolean
    False, ``mode=paper`` the string ``'paper'``; an empty value is the empty string and text
    that is not valid YAML is taken as it is. The keys are checked by
    :meth:`KentRegConfig.with_updates`, not here.

    Raises
    ------
    ConfigError
        An item without ``=`` or with an empty key.
    """
    updates: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition('=')
        if not sep or not key.strip():
            raise ConfigError(f'Expected KEY=VALUE, got {item!r}.')
        try:
            updates[key.strip()] = load_yaml(text) if text.strip() else ''
        except yaml.YAMLError:
            updates[key.strip()] = text
    return updates
