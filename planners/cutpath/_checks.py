"""Argument checks shared by the cut-path modules: every bad input is a ValueError naming it."""

from __future__ import annotations

import math

import numpy as np


def points(xyz, name: str, min_count: int = 1) -> np.ndarray:
    """(N,3) finite float64, at least `min_count` rows."""
    a = np.asarray(xyz, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {a.shape}")
    if len(a) < min_count:
        raise ValueError(f"{name} is empty" if len(a) == 0 else f"{name} needs at least {min_count} points, got {len(a)}")
    if not np.all(np.isfinite(a)):
        bad = int(np.count_nonzero(~np.all(np.isfinite(a), axis=1)))
        raise ValueError(f"{name} contains NaN or inf ({bad} rows)")
    return a


def positive(x, name: str) -> float:
    try:
        v = float(x)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a positive number, got {x!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be a finite positive number, got {x!r}")
    return v


def non_negative(x, name: str) -> float:
    try:
        v = float(x)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a non-negative number, got {x!r}") from None
    if not (math.isfinite(v) and v >= 0):
        raise ValueError(f"{name} must be a finite non-negative number, got {x!r}")
    return v
