"""The parameter file the node and the command lines share: read (a ROS 2 parameter file or a
plain mapping, plus the command lines' ``--set`` overrides) and written (every parameter under
``/**: ros__parameters:``, then the research fields that differ from their defaults).

What the parameters are, their defaults and their validation is :mod:`kentreg_ros.io.params`;
this module only moves them between files and :class:`~kentreg_ros.io.params.Settings`.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import yaml

from kentreg_ros.core import ConfigError, KentRegConfig, flatten_keys, nest_keys
from kentreg_ros.io.params import (
    CORE_PARAMETERS,
    NODE_NAME,
    NodeSettings,
    Settings,
    apply_parameters,
    product_values,
)
from kentreg_ros.io.yamlfile import load_yaml, parse_overrides


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


def dump_parameter_file(
    config: KentRegConfig | None = None, node: NodeSettings | None = None
) -> str:
    """The parameter file of ``config`` and ``node`` (default: the shipped defaults): every
    parameter under ``/**: ros__parameters:``, then the research fields that differ from
    their defaults (dotted; the command lines read them, the node warns that they are not its
    own)."""
    cfg = config if config is not None else KentRegConfig()
    params = product_values(cfg, node if node is not None else NodeSettings())
    behind = set(CORE_PARAMETERS.values())
    defaults = KentRegConfig().to_flat_dict()
    research = {
        k: v for k, v in cfg.to_flat_dict().items() if k not in behind and v != defaults[k]
    }
    header = (
        '# kentreg parameters: read by kentreg_node (ros2 run / launch: --params-file) and by\n'
        '# kentreg_replay --config. Every key is documented in docs/configuration.md.\n'
        '# Regenerate: python3 -m kentreg_ros.docs --parameter-file > config/kentreg.yaml\n'
    )
    body = yaml.safe_dump({'/**': {'ros__parameters': params}}, sort_keys=False)
    if research:
        body += (
            yaml.safe_dump({'research': research}, sort_keys=False)
            .replace('research:\n', '    # research settings (command lines only):\n')
            .replace('\n  ', '\n    ')
        )
    return header + body


def load_settings(
    path: str | Path | None = None,
    overrides: Iterable[str] | Mapping[str, Any] = (),
    *,
    node_name: str = NODE_NAME,
) -> Settings:
    """A run's settings: a parameter file (or the defaults) plus overrides, parameters and
    research fields alike (the command lines' ``--config`` and ``--set``).

    Raises
    ------
    ConfigError
        Unreadable file, unknown key (the message lists the valid ones), invalid value or
        malformed item.
    """
    settings = Settings(KentRegConfig(), NodeSettings())
    if path is not None:
        settings = apply_parameters(parameters_from_yaml(path, node_name))
    updates = dict(overrides) if isinstance(overrides, Mapping) else parse_overrides(overrides)
    if updates:
        settings = apply_parameters(updates, config=settings.config, node=settings.node)
    return settings


def load_config(path: str | Path, node_name: str = NODE_NAME) -> KentRegConfig:
    """The core configuration of a parameter file (its node parameters validated, unused)."""
    return load_settings(path, node_name=node_name).config


def effective_config(
    path: str | Path | None = None, overrides: Iterable[str] | Mapping[str, Any] = ()
) -> KentRegConfig:
    """The core configuration of a run: a parameter file (or the defaults) plus overrides
    (see :func:`load_settings`)."""
    return load_settings(path, overrides).config


def dump_config(config: KentRegConfig) -> str:
    """The parameter file of ``config`` with the node's defaults (loadable by both
    consumers)."""
    return dump_parameter_file(config)
