"""Configuration fields: their metadata (a description, a range or choices), their validation and
coercion, and the walk over a tree of dataclass sections. The one validation path of every
configuration (:mod:`kentreg_ros.core.config`, :mod:`kentreg_ros.io.params`)."""

from __future__ import annotations

import dataclasses
import types
from collections.abc import Iterator, Mapping
from dataclasses import field, fields, is_dataclass
from enum import StrEnum
from typing import Any, ClassVar, get_type_hints

from kentreg_ros.core.errors import ConfigError


def setting(
    default: Any,
    description: str,
    *,
    range: tuple[float, float] | None = None,
    choices: tuple[str, ...] | None = None,
) -> Any:
    """A field with its metadata: a description, and a numeric ``range`` (inclusive) or a tuple
    of ``choices`` (the values of a :class:`~enum.StrEnum` default, when not given)."""
    meta: dict[str, Any] = {'description': description}
    if range is not None:
        meta['range'] = range
    if choices is None and isinstance(default, StrEnum):
        choices = tuple(m.value for m in type(default))
    if choices is not None:
        meta['choices'] = choices
    return field(default=default, metadata=meta)


class Section:
    """A section of the configuration tree: every field is validated when an instance is made,
    however it is made (directly, :meth:`KentRegConfig.from_dict`, ``with_updates``, the node's
    parameters): :func:`coerce_value` by the field's type (an integral float is an integer, an
    integer a float; nothing else changes type), then :func:`validate_value` by its metadata.
    Rules that tie fields together live in :meth:`check`.
    """

    #: Dotted prefix of the section's fields in messages and parameter names (``'em.'``).
    prefix: ClassVar[str] = ''

    def __init_subclass__(cls, *, prefix: str = '', **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        cls.prefix = prefix

    def __post_init__(self) -> None:
        validate_fields(self, self.prefix)
        self.check()

    def check(self) -> None:
        """Cross-field rules of the section (none by default); raise ConfigError."""


def validate_fields(obj: Any, prefix: str = '') -> None:
    """Coerce and validate every scalar field of the dataclass ``obj`` in place (see
    :class:`Section`); sections inside it validate themselves.

    Raises
    ------
    ConfigError
        Naming ``prefix + field``, what was expected and the value given.
    """
    hints = get_type_hints(type(obj))
    for f in fields(obj):
        value = getattr(obj, f.name)
        if is_dataclass(value):
            continue
        coerced = coerce_value(prefix + f.name, value, hints[f.name])
        validate_value(prefix + f.name, coerced, f.metadata)
        if coerced is not value:
            object.__setattr__(obj, f.name, coerced)


def plain_value(value: Any) -> Any:
    """``value`` as YAML and ROS parameters hold it (an enumeration as its string)."""
    return value.value if isinstance(value, StrEnum) else value


def iter_fields(config: Any, prefix: str = '') -> Iterator[tuple[str, Any, dataclasses.Field]]:
    """Yield ``(dotted_name, value, dataclass_field)`` for every leaf field of the tree."""
    for f in fields(config):
        value = getattr(config, f.name)
        name = f'{prefix}{f.name}'
        if is_dataclass(value):
            yield from iter_fields(value, name + '.')
        else:
            yield name, value, f


def validate_value(name: str, value: Any, meta: Mapping[str, Any]) -> None:
    """Check ``value`` against a field's metadata: among ``choices``, within ``range``.

    ``meta`` is the metadata of a field as :func:`setting` writes it (the node's own parameters in
    :mod:`kentreg_ros.io.params` carry the same keys, so both are validated here).

    Raises
    ------
    ConfigError
        Naming ``name``, the allowed values and the value given.
    """
    if 'choices' in meta and value not in meta['choices']:
        raise ConfigError(
            f'Expected `{name}` to be one of {list(meta["choices"])}, got {value!r}.'
        )
    if 'range' in meta:
        lo, hi = meta['range']
        if isinstance(value, bool) or not isinstance(value, int | float) or not lo <= value <= hi:
            raise ConfigError(f'Expected `{name}` in [{lo}, {hi}], got {value!r}.')


def nest_keys(data: Mapping[str, Any]) -> dict[str, Any]:
    """``{'em.max_iterations': 9}`` and ``{'em': {...}}`` alike as one nested mapping.

    Raises
    ------
    ConfigError
        A key that is not a string, or one that is both a section and a scalar.
    """
    out: dict[str, Any] = {}
    for key, value in data.items():
        if not isinstance(key, str):
            raise ConfigError(f'Configuration keys must be strings, got {key!r}.')
        parts = key.split('.')
        node = out
        for part in parts[:-1]:
            child = node.setdefault(part, {})
            if not isinstance(child, dict):
                raise ConfigError(f'Configuration key {key!r} conflicts with a scalar value.')
            node = child
        if isinstance(value, Mapping):
            existing = node.setdefault(parts[-1], {})
            if not isinstance(existing, dict):
                raise ConfigError(f'Configuration key {key!r} conflicts with a scalar value.')
            existing.update(nest_keys(value))
        else:
            node[parts[-1]] = value
    return out


def flatten_keys(data: Mapping[str, Any], prefix: str = '') -> dict[str, Any]:
    """A nested mapping as ``{'em.max_iterations': 9, ...}`` (dotted ROS parameter names)."""
    out: dict[str, Any] = {}
    for key, value in data.items():
        if isinstance(value, Mapping):
            out.update(flatten_keys(value, f'{prefix}{key}.'))
        else:
            out[f'{prefix}{key}'] = value
    return out


def coerce_value(name: str, value: Any, hint: Any) -> Any:
    """``value`` as the type ``hint`` (bool, int, float, str; ``X | None`` as X) or ConfigError.

    Integers are accepted for floats and integral floats for integers; booleans only for bool.
    Other hints return ``value`` unchanged.
    """
    if isinstance(hint, types.UnionType):
        hint = hint.__args__[0]
    if isinstance(hint, type) and issubclass(hint, StrEnum):
        if isinstance(value, bool):
            # YAML 1.1, which ROS parameter files and `-p name:=value` are read with, turns an
            # unquoted off/on (and no/yes, false/true) into a boolean: `deskew: off` or
            # `registered_cloud:=off` arrive as False. Read them as the choice they spell.
            spelled = 'on' if value else 'off'
            if spelled in [m.value for m in hint]:
                return hint(spelled)
        try:
            return hint(value)
        except ValueError:
            valid = [m.value for m in hint]
            raise ConfigError(f'Expected `{name}` to be one of {valid}, got {value!r}.') from None
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f'Expected `{name}` to be true or false, got {value!r}.')
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer():
                return int(value)
            raise ConfigError(f'Expected `{name}` to be an integer, got {value!r}.')
        return value
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f'Expected `{name}` to be a number, got {value!r}.')
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(f'Expected `{name}` to be a string, got {value!r}.')
        return value
    return value
