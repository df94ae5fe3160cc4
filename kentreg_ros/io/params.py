"""Parameter files: the YAML that ``kentreg_node`` and the command lines share.

One file, in the ROS 2 form ``kentreg_node: {ros__parameters: {...}}``, configures the node
(``--params-file``) and every command line (``--config``); the keys are the dotted names of
:class:`~kentreg_ros.core.config.KentRegConfig` fields (``em.max_iterations``), nested or dotted.
The node's own ``node.*`` keys live in the same file and are skipped by :func:`load_config`.
``--set KEY=VALUE`` items (:func:`parse_overrides`) override single keys on top of a file.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import yaml

from kentreg_ros.core import ConfigError
from kentreg_ros.core.config import KentRegConfig, flatten_keys, nest_keys

#: The node's name: the top key of the parameter file.
NODE_NAME = 'kentreg_node'


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


def parameters_from_yaml(path: str | Path, node_name: str = NODE_NAME) -> dict[str, Any]:
    """Read a parameter file and return its flat ``{dotted_name: value}`` mapping.

    Accepts the ROS 2 form ``<node_name>: {ros__parameters: {...}}`` (the node key may carry
    a namespace, ``/ns/<node_name>`` or ``/**/<node_name>``, or be ``/**``) and a plain mapping
    of the same keys, nested or dotted.

    Raises
    ------
    ConfigError
        Unreadable file, invalid YAML, or no mapping at the top.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError(
            f'Cannot read configuration file {str(path)!r}: {exc.strerror}.'
        ) from exc
    try:
        data = load_yaml(text) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f'Configuration file {str(path)!r} is not valid YAML: {exc}.') from exc
    if not isinstance(data, dict):
        raise ConfigError(f'Expected a mapping at the top of {str(path)!r}, got {type(data)}.')
    # ROS keys name the node: `kentreg_node`, `/kentreg_node`, `/robot1/kentreg_node`,
    # `/**/kentreg_node` (any namespace) or `/**` (every node).
    keys = [k for k in data if isinstance(k, str)]
    candidates = [k for k in keys if k in (node_name, '/' + node_name)]
    candidates += [k for k in keys if k.endswith('/' + node_name) and k not in candidates]
    candidates += [k for k in keys if k == '/**']
    for key in candidates:
        section = data.get(key)
        if isinstance(section, dict) and 'ros__parameters' in section:
            data = section['ros__parameters'] or {}
            break
    return flatten_keys(nest_keys(data))


def load_config(
    path: str | Path, node_name: str = NODE_NAME, ignore_prefixes: tuple[str, ...] = ('node.',)
) -> KentRegConfig:
    """Load a :class:`KentRegConfig` from a YAML file (see :func:`parameters_from_yaml`).

    Keys under ``ignore_prefixes`` belong to the ROS node only and are skipped here.

    Raises
    ------
    ConfigError
        An unreadable file, an unknown key (the message lists the valid ones) or a bad value.
    """
    params = parameters_from_yaml(path, node_name)
    params = {k: v for k, v in params.items() if not k.startswith(ignore_prefixes)}
    return KentRegConfig.from_dict(params)


def dump_config(config: KentRegConfig, node_name: str = NODE_NAME) -> str:
    """YAML text in the ``<node_name>: ros__parameters:`` form, loadable by both consumers."""
    return yaml.safe_dump({node_name: {'ros__parameters': config.to_dict()}}, sort_keys=False)


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


def effective_config(
    path: str | Path | None = None, overrides: Iterable[str] | Mapping[str, Any] = ()
) -> KentRegConfig:
    """The configuration of a run: a parameter file (or the defaults) plus overrides.

    Parameters
    ----------
    path : str or Path, optional
        A parameter file (see :func:`load_config`); None for the defaults.
    overrides : iterable of str, or mapping
        ``KEY=VALUE`` items (see :func:`parse_overrides`) or a ``{dotted_key: value}`` mapping,
        applied in order on top of the file.

    Raises
    ------
    ConfigError
        Unreadable file, unknown key, invalid value or malformed item.
    """
    cfg = load_config(path) if path is not None else KentRegConfig()
    updates = dict(overrides) if isinstance(overrides, Mapping) else parse_overrides(overrides)
    return cfg.with_updates(updates) if updates else cfg
