"""One summary of a sample for every bench figure: n, min, median, p90, p99, max. The tail percentiles
are nearest-rank (numpy's "inverted_cdf": the smallest value with at least that share of the sample at
or below it), so each is a value that was measured; the median is the usual one (the mean of the
middle two of an even sample)."""

from __future__ import annotations

import numpy as np


def summary(xs) -> dict | None:
    """None for an empty sample; values rounded to 3 decimals (µs when ``xs`` are milliseconds)."""
    a = np.asarray(list(xs), dtype=np.float64)
    if a.size == 0:
        return None
    p90, p99 = np.percentile(a, [90, 99], method="inverted_cdf")
    return {"n": int(a.size), "min": round(float(a.min()), 3), "median": round(float(np.median(a)), 3),
            "p90": round(float(p90), 3), "p99": round(float(p99), 3), "max": round(float(a.max()), 3)}
