"""Flat parameter mappings (a ROS ``--params-file`` YAML, ``KEY=VALUE`` overrides) -> frozen config
dataclasses, ROS-free.

One field = one parameter named ``prefix + field``, as :func:`ga_ros.ros.params.declare_config`
declares them for the nodes: the replay reads ``config/vo.yaml`` (or single overrides) through
:func:`config_from_params` into the same dataclasses with the same coercion
(:func:`coerce_value`: a float field accepts an integer, nothing else changes type).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import fields, replace
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from ga_ros.errors import InputError

C = TypeVar('C')


def coerce_value(name: str, default: Any, value: Any) -> Any:
    """``value`` of parameter ``name`` in the type of its ``default``.

    Floats accept integers (``-p tolerance:=1``); booleans, integers and strings must match.

    Raises
    ------
    InputError
        A value of another type (e.g. a string for a number).
    """
    if isinstance(default, np.generic):
        default = default.item()
    if isinstance(default, bool):
        ok = isinstance(value, bool)
    elif isinstance(default, int):
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif isinstance(default, float):
        ok = isinstance(value, int | float) and not isinstance(value, bool)
        value = float(value) if ok else value
    else:
        ok = isinstance(value, type(default))
    if not ok:
        raise InputError(f'parameter {name} must be a {type(default).__name__}, got {value!r}')
    return value


def config_from_params(cls: type[C], params: Mapping[str, Any], prefix: str = '',
                       base: C | None = None) -> tuple[C, set[str]]:
    """Build ``cls`` from the parameters named ``prefix + field`` (others are left alone).

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
        A value of the wrong type, or one the dataclass rejects.
    """
    base = cls() if base is None else base
    values, used = {}, set()
    for f in fields(cls):  # type: ignore[arg-type]
        name = prefix + f.name
        if name in params:
            values[f.name] = coerce_value(name, getattr(base, f.name), params[name])
            used.add(name)
    try:
        return replace(base, **values), used  # type: ignore[type-var]
    except (TypeError, ValueError) as exc:
        raise InputError(f'bad {cls.__name__} parameters: {exc}') from exc


def read_params_file(path: str | Path, node: str = '') -> dict[str, Any]:
    """The parameters of a ROS ``--params-file`` YAML (``node: {ros__parameters: {...}}``;
    ``node`` '' = the only node in the file, or ``/**``) or of a flat ``{name: value}`` YAML.

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
        return dict(data)
    key = node if node in nodes else ('/**' if '/**' in nodes else '')
    if not key and len(nodes) == 1:
        key = next(iter(nodes))
    if not key:
        raise InputError(f'parameter file {path} has parameters of {sorted(nodes)}; '
                         f'expected one node or {node!r}')
    return dict(nodes[key])


def parse_override(text: str) -> tuple[str, Any]:
    """``'KEY=VALUE'`` -> ``(key, value)``, the value read as YAML (``0.5``, ``true``, ``abc``).

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
    return key.strip(), value
