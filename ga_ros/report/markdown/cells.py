"""Table cells of the report: figures formatted, a missing or non-finite one as ``-``."""

from __future__ import annotations

import numpy as np


def fixed(x: float | None, nd: int = 1) -> str:
    """A figure with ``nd`` decimals (``1.2``), ``-`` when missing or not finite."""
    return '-' if x is None or not np.isfinite(x) else f'{x:.{nd}f}'


def signed(x: float | None, nd: int = 1) -> str:
    """A signed figure (``+1.2``), ``-`` when missing or not finite."""
    return '-' if x is None or not np.isfinite(x) else f'{x:+.{nd}f}'


def interval(d: dict) -> str:
    """``mean [low, high]`` of a paired difference (``policy_statistics``), one draw: mean."""
    if d['n'] < 2:
        return f'{signed(d["mean"])} (one draw)'
    return f'{signed(d["mean"])} [{signed(d["ci_low"])}, {signed(d["ci_high"])}]'
