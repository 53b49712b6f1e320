"""Numeric ranges of config fields, declared once on the field and checked everywhere.

A config dataclass declares a number's allowed interval on the field itself (:func:`ranged`
is ``field(default=5, metadata={'range': (1, 1000)})``)::

    window_tracks: int = ranged(5, 1, 1000)

Its ``__post_init__`` calls :func:`check_ranges`; :func:`ga_ros.ros.params.declare_config`
gives the same interval to the ROS parameter descriptor, and both the node and
:func:`ga_ros.pipeline.params.config_from_params` (the replay) report a value outside it with
:func:`range_message`, so every entry point refuses the same values with the same words.
"""

from __future__ import annotations

import numbers
from dataclasses import field, fields
from typing import Any

from ga_ros.errors import InputError


def ranged(default: Any, lo: float, hi: float) -> Any:
    """A dataclass field with a default and its allowed closed interval ``[lo, hi]``."""
    return field(default=default, metadata={'range': (lo, hi)})


def string_list(default: tuple[str, ...] = ()) -> Any:
    """A dataclass field holding names, a ``tuple[str, ...]`` (``metadata['items'] = str``):
    a ROS ``STRING_ARRAY`` parameter (:func:`ga_ros.ros.params.declare_config`), a YAML list;
    a comma-separated string is accepted too (:func:`names_of`)."""
    return field(default=tuple(default), metadata={'items': str})


def names_of(value: Any) -> tuple[str, ...]:
    """The names of a :func:`string_list` value: a sequence of strings, or one string of
    comma-separated names (``'cam0, cam1'``); blanks stripped, empty names dropped.

    Raises
    ------
    InputError
        Anything else (a number, a list holding one).
    """
    if isinstance(value, str):
        items = value.split(',')
    elif isinstance(value, list | tuple) and all(isinstance(v, str) for v in value):
        items = list(value)
    else:
        raise InputError(f'a list of names (or one comma-separated string) expected, '
                         f'got {value!r}')
    return tuple(n.strip() for n in items if n.strip())


def field_range(cls: type, name: str) -> tuple[float, float] | None:
    """The closed interval ``(lo, hi)`` declared on field ``name`` of dataclass ``cls``
    (``metadata['range']``), None without one."""
    for f in fields(cls):  # type: ignore[arg-type]
        if f.name == name:
            return f.metadata.get('range')
    return None


def range_message(owner: str, name: str, value: Any, rng: tuple[float, float]) -> str | None:
    """The refusal of ``value`` for field ``owner.name`` with interval ``rng``; None inside it.

    Parameters
    ----------
    owner : the config class name (``'AlignerConfig'``).
    name : the field name.
    value : the value (a number; NaN is outside every interval).
    rng : ``(lo, hi)``, both included.
    """
    lo, hi = rng
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        return None  # a type error is reported elsewhere (coerce_value, the dataclass user)
    if lo <= value <= hi:  # False for NaN: refused
        return None
    return f'{owner}.{name} = {value!r} is outside [{lo:g}, {hi:g}]'


def check_ranges(config: Any) -> None:
    """Raise :class:`~ga_ros.errors.InputError` for the first field of the dataclass instance
    ``config`` whose value lies outside its declared ``metadata['range']``.

    Raises
    ------
    InputError
        A value outside its range (message from :func:`range_message`).
    """
    owner = type(config).__name__
    for f in fields(config):
        rng = f.metadata.get('range')
        if rng is None:
            continue
        msg = range_message(owner, f.name, getattr(config, f.name), rng)
        if msg:
            raise InputError(msg)
