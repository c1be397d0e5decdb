"""Robustness arithmetic over rain rates (Michaelis et al. 2019, "Benchmarking Robustness in Object
Detection"): percent drop, mPC, rPC and the rate at which a metric falls to half its clean value.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

def percent_drop(clean: float | np.ndarray, value: float | np.ndarray) -> float | np.ndarray:
    """Relative degradation in percent: ``100 * (clean - value) / clean``.

    Positive means worse than clean (the paper's "% drop"); nan where ``clean == 0`` or either
    input is nan.

    Args:
        clean: Scalar or (...) float array, the metric at rate 0.
        value: Scalar or array broadcastable with ``clean``, the metric under rain.

    Returns:
        float for scalar inputs, else float64 array of the broadcast shape.
    """
    clean_array = np.asarray(clean, dtype=np.float64)
    value_array = np.asarray(value, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        drop = np.where(clean_array == 0, np.nan, 100.0 * (clean_array - value_array) / clean_array)
    return float(drop) if drop.ndim == 0 else drop


def _rates_and_values(values_by_rate: Mapping[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """(R,) float64 rates and (R,) float64 values of a ``{rate: value}`` mapping, validated."""
    if not values_by_rate:
        raise ValueError("values_by_rate: expected {rate_mm_h: value} with at least one rate, got an empty mapping")
    rates = np.array([float(r) for r in values_by_rate], dtype=np.float64)
    values = np.array([float(v) for v in values_by_rate.values()], dtype=np.float64)
    if np.any(rates < 0) or not np.all(np.isfinite(rates)):
        raise ValueError(f"values_by_rate: expected finite rates >= 0 mm/h, got {rates.tolist()}")
    return rates, values


def mpc(values_by_rate: Mapping[float, float]) -> float:
    """Mean performance under corruption: the mean of the metric over rates > 0.

    Args:
        values_by_rate: ``{rate_mm_h: metric}``; rates > 0 are averaged with equal weight
            (nan propagates).

    Returns:
        mPC as a float.
    """
    rates, values = _rates_and_values(values_by_rate)
    rainy = rates > 0
    if not rainy.any():
        raise ValueError(f"values_by_rate: expected at least one rate > 0 mm/h, got {rates.tolist()}")
    return float(np.mean(values[rainy]))


def rpc(values_by_rate: Mapping[float, float]) -> float:
    """Relative performance under corruption: ``mPC / P`` with P the metric at rate 0.

    Args:
        values_by_rate: ``{rate_mm_h: metric}`` including rate 0.

    Returns:
        rPC as a float; nan when P is 0 or nan.
    """
    rates, values = _rates_and_values(values_by_rate)
    clean = values[rates == 0]
    if len(clean) != 1:
        raise ValueError(f"values_by_rate: expected exactly one rate 0 (clean), got rates {rates.tolist()}")
    performance_clean = float(clean[0])
    if performance_clean == 0 or math.isnan(performance_clean):
        return float("nan")
    return mpc(values_by_rate) / performance_clean


def half_value_rate(values_by_rate: Mapping[float, float], fraction: float = 0.5) -> float:
    """The rain rate at which a metric first falls to ``fraction`` of its clean (rate 0) value.

    Linear interpolation between the two measured rates around the crossing. Returns inf when
    the metric stays above ``fraction x clean`` at every measured rate, and nan when the clean
    value is 0 or nan.

    Args:
        values_by_rate: ``{rate_mm_h: metric}`` including rate 0.
        fraction: Level, in (0, 1), relative to the clean value.
    """
    if not 0 < fraction < 1:
        raise ValueError(f"fraction: expected a value in (0, 1), got {fraction}")
    rates, values = _rates_and_values(values_by_rate)
    order = np.argsort(rates)
    rates, values = rates[order], values[order]
    if rates[0] != 0:
        raise ValueError(f"values_by_rate: expected rate 0 (clean), got rates {rates.tolist()}")
    clean = values[0]
    if clean == 0 or math.isnan(clean):
        return float("nan")
    level = fraction * clean
    for index in range(1, len(rates)):
        if values[index] <= level:
            previous, current = values[index - 1], values[index]
            if previous == current:
                return float(rates[index])
            step = (previous - level) / (previous - current)
            return float(rates[index - 1] + step * (rates[index] - rates[index - 1]))
    return float("inf")
