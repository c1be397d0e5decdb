"""The camera's tone curve: display values (what images store) to linear light and back.

Light adds and mixes linearly (Koschmieder's extinction and airlight, a drop covering a pixel for
part of the exposure, spray lit by the sky, a mirror on water); images hold display values, the
linear light through a 1/2.2 tone curve. Mixing display values directly weights dark values too
heavily: a 50/50 mix of 0 and 255 is 186 in light, not 128.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np

DISPLAY_LIGHT_GAMMA = 2.2
"""The camera maps relative luminance to display values with exponent 1/2.2, so a 10x dimmer
patch is 0.35x, not 0.1x, as bright in the image."""


@functools.lru_cache(maxsize=1)
def _linear_table() -> np.ndarray:
    return np.power(np.arange(256, dtype=np.float32) / np.float32(255.0), np.float32(DISPLAY_LIGHT_GAMMA))


def to_linear(display: np.ndarray) -> np.ndarray:
    """Linear light in [0, 1], float32, of uint8 display values (any shape): ``(v / 255)^2.2``."""
    display = np.asarray(display)
    if display.dtype != np.uint8:
        raise TypeError(f"display: expected uint8 values, got {display.dtype}")
    if display.ndim == 3 and display.size and display.shape[2] <= 4:  # an image: OpenCV's lookup, 9x numpy's
        return cv2.LUT(display, _linear_table()).reshape(display.shape)
    return _linear_table()[display]


def linear_value(display: float | np.ndarray) -> np.ndarray:
    """Linear light of display values given as numbers in [0, 255] (a colour, an airlight):
    ``(v / 255)^2.2`` in float64."""
    return (np.clip(np.asarray(display, dtype=np.float64), 0.0, 255.0) / 255.0) ** DISPLAY_LIGHT_GAMMA


def to_display(linear: np.ndarray) -> np.ndarray:
    """uint8 display values of linear light (float32, any shape; clipped to [0, 1], so +inf is
    255): ``round(255 x^(1/2.2))``. Returns a new array."""
    linear = np.clip(np.asarray(linear, dtype=np.float32), 0.0, 1.0)  # OpenCV's pow takes |x|
    if linear.size == 0:
        return np.zeros(linear.shape, np.uint8)
    work = linear if 1 <= linear.ndim <= 3 else linear.reshape(-1, 1)  # shapes OpenCV takes
    return cv2.convertScaleAbs(cv2.pow(work, 1.0 / DISPLAY_LIGHT_GAMMA), alpha=255.0).reshape(linear.shape)
