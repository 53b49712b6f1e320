"""Flat parameter mappings (a ROS ``--params-file`` YAML, ``KEY=VALUE`` overrides) -> frozen config
dataclasses, ROS-free.

One field = one parameter named ``prefix + field``, as :func:`ga_ros.ros.params.declare_config`
declares them for the nodes; a field holding a config dataclass (``AlignerConfig.solver``) gives
one dotted parameter per nested field (``solver.tolerance``), as ROS names a nested YAML mapping
(:func:`flat_params`). The replay reads ``config/vo.yaml`` (or single overrides) through
:func:`config_from_params` into the same dataclasses with the same coercion
(:func:`coerce_value`: a float field accepts an integer, nothing else changes type).
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import fields, is_dataclass, replace
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from ga_ros.core.config_ranges import names_of
from ga_ros.core.tracks import TrackRules, refuse_former_names
from ga_ros.errors import InputError

C = TypeVar('C')

_EXPONENT_FLOAT = re.compile(r'[-+]?(\d+\.?\d*|\.\d+)[eE][-+]?\d+')


def coerce_value(name: str, default: Any, value: Any, items: type | None = None) -> Any:
    """``value`` of parameter ``name`` in the type of its ``default``.

    Floats accept integers (``-p tolerance:=1``); a tuple (of floats) accepts any list of numbers;
    a tuple of names (``items`` ``str``: a field of
    :func:`~ga_ros.core.config_ranges.string_list`) a list of strings or one comma-separated
    string; booleans, integers and strings must match.

    Raises
    ------
    InputError
        A value of another type (e.g. a string for a number).
    """
    if isinstance(default, np.generic):
        default = default.item()
    if items is str:   # names (a ROS string array; a comma-separated string too)
        try:
            return names_of(value)
        except InputError:
            raise InputError(f'parameter {name} must be a list of names, got {value!r}') from None
    if isinstance(default, bool):
        ok = isinstance(value, bool)
    elif isinstance(default, int):
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif isinstance(default, float):
        ok = isinstance(value, int | float) and not isinstance(value, bool)
        value = float(value) if ok else value
    elif isinstance(default, tuple):  # a list of numbers (ROS double array, YAML list)
        items = list(value) if not isinstance(value, str | bytes | dict) else None
        ok = items is not None and all(isinstance(v, int | float | np.floating | np.integer)
                                       and not isinstance(v, bool) for v in items)
        value = tuple(float(v) for v in items) if ok else value
    else:
        ok = isinstance(value, type(default))
    if not ok:
        raise InputError(f'parameter {name} must be a {type(default).__name__}, got {value!r}')
    return value


def config_from_params(cls: type[C], params: Mapping[str, Any], prefix: str = '',
                       base: C | None = None) -> tuple[C, set[str]]:
    """Build ``cls`` from the parameters named ``prefix + field`` (others are left alone); a
    nested config dataclass field from ``prefix + field + '.' + nested field``.

    Parameters
    ----------
    cls : frozen dataclass with defaults for every field.
    params : ``{parameter name: value}``.
    prefix : prepended to each field name (e.g. ``'cross_'``).
    base : values of the fields not in ``params`` (default: ``cls()``).

    Returns
    -------
    (config, names) : the config and the parameter names it used.

    Raises
    ------
    InputError
        A value of the wrong type, one the dataclass rejects (a value outside a field's
        ``metadata['range']``: :func:`ga_ros.core.config_ranges.range_message`), or a
        flat track setting (``odom0.track_mode``; the nested name is ``odom0.track.mode``).
    """
    base = cls() if base is None else base
    values, used = {}, set()
    for f in fields(cls):  # type: ignore[arg-type]
        name = prefix + f.name
        nested = getattr(base, f.name)
        if is_dataclass(nested):
            if isinstance(nested, TrackRules):
                refuse_former_names(params, prefix, f.name)
            values[f.name], inner = config_from_params(type(nested), params, name + '.', nested)
            used |= inner
        elif name in params:
            values[f.name] = coerce_value(name, getattr(base, f.name), params[name],
                                          f.metadata.get('items'))
            used.add(name)
    try:
        return replace(base, **values), used  # type: ignore[type-var]
    except InputError:
        raise  # the dataclass's own words (a range: the same as the node's)
    except (TypeError, ValueError) as exc:
        raise InputError(f'bad {cls.__name__} parameters: {exc}') from exc


def read_params_file(path: str | Path, node: str = '') -> dict[str, Any]:
    """The parameters of a ROS ``--params-file`` YAML (``node: {ros__parameters: {...}}``;
    ``node`` '' = the only node in the file, or ``/**``) or of a flat ``{name: value}`` YAML,
    nested mappings as dotted names (:func:`flat_params`).

    Raises
    ------
    InputError
        An unreadable file, or one that is neither form.
    """
    import yaml

    try:
        data = yaml.safe_load(Path(path).read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise InputError(f'cannot read parameter file {path}: {exc}') from exc
    if not isinstance(data, dict):
        raise InputError(f'parameter file {path} is not a YAML mapping')
    nodes = {k: v['ros__parameters'] for k, v in data.items()
             if isinstance(v, dict) and isinstance(v.get('ros__parameters'), dict)}
    if not nodes:
        return flat_params(data)
    key = node if node in nodes else ('/**' if '/**' in nodes else '')
    if not key and len(nodes) == 1:
        key = next(iter(nodes))
    if not key:
        raise InputError(f'parameter file {path} has parameters of {sorted(nodes)}; '
                         f'expected one node or {node!r}')
    return flat_params(nodes[key])


def flat_params(params: Mapping[str, Any], prefix: str = '') -> dict[str, Any]:
    """``{'solver': {'tolerance': 1e-6}}`` -> ``{'solver.tolerance': 1e-6}``: nested mappings of a
    parameter file as the dotted parameter names ROS gives them."""
    out: dict[str, Any] = {}
    for key, value in params.items():
        if isinstance(value, Mapping):
            out.update(flat_params(value, f'{prefix}{key}.'))
        else:
            out[f'{prefix}{key}'] = value
    return out


def parse_override(text: str) -> tuple[str, Any]:
    """``'KEY=VALUE'`` -> ``(key, value)``, the value read as YAML (``0.5``, ``true``, ``abc``;
    ``1e-6`` as a float, as ROS reads it); ``KEY`` may be dotted (``solver.tolerance``).

    Raises
    ------
    InputError
        Without ``=``.
    """
    import yaml

    key, sep, raw = text.partition('=')
    if not sep or not key.strip():
        raise InputError(f'expected KEY=VALUE, got {text!r}')
    try:
        value = yaml.safe_load(raw) if raw.strip() else ''
    except yaml.YAMLError:
        value = raw
    if isinstance(value, str) and _EXPONENT_FLOAT.fullmatch(value.strip()):
        value = float(value)  # YAML 1.1 reads 1e-6 as a string; ROS (-p x:=1e-6) as a double
    return key.strip(), value


def parameter_names(cls: type, prefix: str = '') -> list[str]:
    """Names of the parameters a node declares for config dataclass ``cls``.

    One name per field (``prefix + field``), dotted names for the fields of a nested config
    dataclass (``solver.tolerance``), exactly as :func:`ga_ros.ros.params.declare_config`
    declares them; used to check launch and parameter files without starting a node.

    Parameters
    ----------
    cls : frozen config dataclass with defaults for every field.
    prefix : prepended to each name (e.g. ``'cross_'``).

    Returns
    -------
    list[str]
        The parameter names, in field order.
    """
    names: list[str] = []
    defaults = cls()
    for f in fields(cls):  # type: ignore[arg-type]
        value = getattr(defaults, f.name)
        if is_dataclass(value):
            names += parameter_names(type(value), f'{prefix}{f.name}.')
        else:
            names.append(prefix + f.name)
    return names
