"""One dataclass -> ROS parameters helper for both nodes.

Every field of a frozen config dataclass becomes one read-only parameter (name = prefix +
field). The description comes from the field's ``metadata['help']``, else from the numpydoc
``Attributes`` section of the class; the numeric range from ``metadata['range']``, else from the
``ranges`` argument. Float parameters accept integers (``-p tolerance:=1``) and are range-checked.
"""

from __future__ import annotations

import re
from dataclasses import Field, fields
from typing import Any, TypeVar

import numpy as np
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.node import Node

from ga_ros.errors import InputError
from ga_ros.pipeline.params import coerce_value

C = TypeVar('C')


def field_docs(cls: type) -> dict[str, str]:
    """``{field: text}`` from the numpydoc ``Attributes`` section of a config dataclass."""
    docs: dict[str, str] = {}
    names: list[str] = []
    for line in (cls.__doc__ or '').splitlines():
        m = re.match(r'^    ([a-z_0-9, ]+) : (.*)$', line)
        if m:
            names = [n.strip() for n in m.group(1).split(',')]
            for n in names:
                docs[n] = m.group(2).strip()
        elif names and line.startswith('        ') and line.strip():
            for n in names:
                docs[n] += ' ' + line.strip()
        else:
            names = []
    return docs


def descriptor(name: str, default: object, text: str,
               rng: tuple[float, float] | None = None) -> ParameterDescriptor:
    """Read-only descriptor of one parameter, with its integer or float range."""
    d = ParameterDescriptor(name=name, description=text, read_only=True)
    if rng is not None and isinstance(default, bool):
        rng = None
    if rng is not None and isinstance(default, int):
        d.integer_range = [IntegerRange(from_value=int(rng[0]), to_value=int(rng[1]), step=1)]
    elif isinstance(default, float):
        d.dynamic_typing = True  # accept 1 as well as 1.0 (coerced and checked in declare)
        if rng is not None:
            d.floating_point_range = [FloatingPointRange(from_value=float(rng[0]),
                                                         to_value=float(rng[1]), step=0.0)]
    return d


def _text(cls: type, f: Field, docs: dict[str, str]) -> str:
    text = f.metadata.get('help') or docs.get(f.name, f.name.replace('_', ' '))
    return f'{cls.__name__}.{f.name}: ' + str(text).replace('``', '')


def declare_config(node: Node, cls: type[C], prefix: str = '',
                   ranges: dict[str, tuple[float, float]] | None = None) -> C:
    """Declare one parameter per field of ``cls`` and build the config from their values.

    Parameters
    ----------
    node : the node declaring the parameters.
    cls : frozen dataclass with defaults for every field.
    prefix : prepended to each parameter name (e.g. ``'cross_'``).
    ranges : numeric ranges of fields without ``metadata['range']``.

    Raises
    ------
    InputError
        A float parameter that is not a number or lies outside its range.
    """
    defaults = cls()
    docs = field_docs(cls)
    values: dict[str, Any] = {}
    for f in fields(cls):  # type: ignore[arg-type]
        default = getattr(defaults, f.name)
        if isinstance(default, np.generic):
            default = default.item()
        rng = f.metadata.get('range') or (ranges or {}).get(f.name)
        desc = descriptor(prefix + f.name, default, _text(cls, f, docs), rng)
        value = node.declare_parameter(prefix + f.name, default, desc).value
        if isinstance(default, float):
            value = coerce_value(prefix + f.name, default, value)  # as the replay does
            for r in desc.floating_point_range:
                if not r.from_value <= value <= r.to_value:
                    raise InputError(f'parameter {prefix + f.name} = {value} is outside '
                                     f'[{r.from_value}, {r.to_value}]')
        values[f.name] = value
    return cls(**values)
