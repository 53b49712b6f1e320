"""One dataclass -> ROS parameters helper for both nodes.

Every field of a frozen config dataclass becomes one parameter (name = prefix + field),
read-only unless named in ``dynamic`` (then :func:`updated_config` applies changes at run time,
from an ``add_on_set_parameters_callback``); a read-only parameter's description ends with the
reason it is read-only. The description comes from the field's ``metadata['help']``, else from
the numpydoc ``Attributes`` section of the class; the numeric range from ``metadata['range']``,
else from the ``ranges`` argument. Float parameters accept integers (``-p tolerance:=1``) and are
range-checked. A field holding a config dataclass (``AlignerConfig.solver``) gives one dotted
parameter per nested field (``solver.max_iterations``, a ``solver:`` mapping in a parameter file),
described from the nested class; ``ranges`` and ``dynamic`` name them the same way.
"""

from __future__ import annotations

import re
from dataclasses import Field, fields, is_dataclass, replace
from typing import Any, TypeVar

import numpy as np
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.node import Node
from rclpy.parameter import Parameter

from ga_ros.core.config_ranges import range_message
from ga_ros.core.tracks import TrackRules, refuse_former_names
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
               rng: tuple[float, float] | None = None,
               read_only: bool = True) -> ParameterDescriptor:
    """Descriptor of one parameter (read-only by default), with its integer or float range."""
    d = ParameterDescriptor(name=name, description=text, read_only=read_only)
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
                   ranges: dict[str, tuple[float, float]] | None = None,
                   dynamic: frozenset[str] = frozenset(),
                   read_only_reason: str = 'fixed at start; restart the node to change it',
                   defaults: C | None = None) -> C:
    """Declare one parameter per field of ``cls`` and build the config from their values.

    Parameters
    ----------
    node : the node declaring the parameters.
    cls : frozen dataclass with defaults for every field.
    prefix : prepended to each parameter name (e.g. ``'cross_'``).
    ranges : numeric ranges of fields without ``metadata['range']`` (nested: dotted names).
    dynamic : fields that may change at run time (not read-only; apply them with
        :func:`updated_config`); nested fields by dotted name (``'solver.tolerance'``).
    read_only_reason : appended to the description of the other (read-only) parameters.
    defaults : default values (default: ``cls()``).

    Raises
    ------
    InputError
        A float parameter that is not a number or lies outside its range.
    """
    defaults = cls() if defaults is None else defaults
    return _declare(node, cls, defaults, prefix, '', ranges or {}, dynamic, read_only_reason)


def _declare(node: Node, cls: type[C], defaults: C, prefix: str, path: str,
             ranges: dict[str, tuple[float, float]], dynamic: frozenset[str],
             read_only_reason: str) -> C:
    """:func:`declare_config` of the fields of ``cls`` named ``path + field`` (``path`` = the
    dotted names of the enclosing fields, '' at the top)."""
    docs = field_docs(cls)
    values: dict[str, Any] = {}
    for f in fields(cls):  # type: ignore[arg-type]
        default = getattr(defaults, f.name)
        key = path + f.name
        if is_dataclass(default):
            if isinstance(default, TrackRules):  # a former flat name would be ignored silently
                refuse_former_names(getattr(node, '_parameter_overrides', {}), prefix + path,
                                    f.name)
            values[f.name] = _declare(node, type(default), default, prefix, key + '.', ranges,
                                      dynamic, read_only_reason)
            continue
        if isinstance(default, np.generic):
            default = default.item()
        rng = f.metadata.get('range') or ranges.get(key)
        live = key in dynamic
        text = _text(cls, f, docs) + (' (can be changed at run time)' if live
                                      else f' (read-only: {read_only_reason})')
        desc = descriptor(prefix + key, default, text, rng, read_only=not live)
        items = f.metadata.get('items')
        if items is str:
            value = _declare_names(node, prefix + key, default, desc)
        else:
            try:
                value = node.declare_parameter(prefix + key, default, desc).value
            except InvalidParameterValueException as exc:  # ROS refused it against the range
                raise InputError(_range_refusal(node, prefix + key, cls.__name__, f.name, rng)
                                 or str(exc)) from exc
        values[f.name] = _checked(prefix + key, default, value, desc, cls.__name__, f.name,
                                  items)
    return cls(**values)


def _declare_names(node: Node, name: str, default: tuple[str, ...],
                   desc: ParameterDescriptor) -> tuple[str, ...] | str:
    """Declare the names field ``name`` (:func:`~ga_ros.core.config_ranges.string_list`) as a
    ``STRING_ARRAY`` parameter (``[cam0, cam1]`` in a parameter file, ``-p
    name:="['cam0']"``), or, where it is given one comma-separated string (``'cam0,cam1'``),
    as a ``STRING`` parameter holding it. A string array cannot be declared with an empty
    default (rclpy would type an empty list a byte array): without a value given, the
    parameter is declared typed and unset, and the field keeps ``default``."""
    override = getattr(node, '_parameter_overrides', {}).get(name)
    if override is not None and override.type_ == Parameter.Type.STRING:
        return node.declare_parameter(name, Parameter.Type.STRING, desc).value
    try:
        if default:
            value = node.declare_parameter(name, list(default), desc).value
        else:
            value = node.declare_parameter(name, Parameter.Type.STRING_ARRAY, desc).value
    except InvalidParameterTypeException as exc:
        raise InputError(f'parameter {name} must be a list of names (a string array, or one '
                         f'comma-separated string): {exc}') from exc
    return default if value is None else tuple(value)


def _range_refusal(node: Node, name: str, owner: str, field_name: str,
                   rng: tuple[float, float] | None) -> str | None:
    """The refusal of the start-up value of parameter ``name`` (field ``owner.field_name``) in
    the words of the config dataclass (:func:`ga_ros.core.config_ranges.range_message`); None
    when it is not a range refusal. rclpy's exception keeps no value, so the value is read from
    the node's parameter overrides."""
    override = getattr(node, '_parameter_overrides', {}).get(name)
    if rng is None or override is None:
        return None
    msg = range_message(owner, field_name, override.value, rng)
    return f'parameter {name}: {msg}' if msg else None


def _checked(name: str, default: object, value: Any, desc: ParameterDescriptor,
             owner: str, field_name: str, items: type | None = None) -> Any:
    """``value`` of parameter ``name`` (field ``owner.field_name``) in the type of ``default``
    (as the replay reads it) and, for a float, within its range (InputError otherwise, with the
    message the config dataclass gives: :func:`ga_ros.core.config_ranges.range_message`)."""
    value = coerce_value(name, default, value, items)
    if isinstance(default, float):
        for r in desc.floating_point_range:
            msg = range_message(owner, field_name, value, (r.from_value, r.to_value))
            if msg:
                raise InputError(f'parameter {name}: {msg}')
    return value


def updated_config(node: Node, config: C, changes: dict[str, Any], prefix: str = '') -> C:
    """``config`` with the changed parameters of its fields applied (others are ignored), nested
    config dataclass fields included (dotted names, as :func:`declare_config` declares them).

    Parameters
    ----------
    node : the node (its parameter descriptors give the ranges).
    config : the current frozen config.
    changes : ``{parameter name: new value}`` (from ``add_on_set_parameters_callback``).
    prefix : the prefix the fields were declared with.

    Raises
    ------
    InputError
        A value of the wrong type, out of range or rejected by the config's own checks.
    """
    own = {f.name: getattr(config, f.name) for f in fields(config)}  # type: ignore[arg-type]
    items = {f.name: f.metadata.get('items') for f in fields(config)}  # type: ignore[arg-type]
    new: dict[str, Any] = {}
    for key, inner in own.items():
        if is_dataclass(inner):
            changed = updated_config(node, inner, changes, f'{prefix}{key}.')
            if changed is not inner:
                new[key] = changed
    for pname, value in changes.items():
        key = pname[len(prefix):] if pname.startswith(prefix) else None
        if key not in own or is_dataclass(own[key]):
            continue
        default = own[key]
        if isinstance(default, np.generic):
            default = default.item()
        desc = node.describe_parameter(pname)
        new[key] = _checked(pname, default, value, desc, type(config).__name__, key,
                            items[key])
        if isinstance(default, bool | str) and type(new[key]) is not type(default):
            raise InputError(f'parameter {pname} must be a {type(default).__name__}')
    if not new:
        return config
    try:
        return replace(config, **new)  # type: ignore[type-var]
    except (TypeError, ValueError) as exc:
        raise InputError(f'rejected: {exc}') from exc
