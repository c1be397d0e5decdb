"""Image-quality statistics of rainy frames: SSIM, PSNR and per-box rain labels.

SSIM convention (seed paper eq. 1; Wang et al. 2004), identical to
``skimage.metrics.structural_similarity(Y1, Y2, gaussian_weights=True, sigma=1.5,
use_sample_covariance=False, data_range=255)`` on BT.601 luma:

* Y = 0.299 R + 0.587 G + 0.114 B, no rounding;
* Gaussian window sigma 1.5 truncated at 3.5 sigma (11 taps, radius 5), normalised, applied
  separably with reflect borders (scipy ``mode='reflect'`` == OpenCV ``BORDER_REFLECT``);
* K1 = 0.01, K2 = 0.03, data range L = 255, population (co)variances;
* the SSIM map is averaged (in float64) after cropping a 5-pixel border.

The SSIM maps are computed in float32: five times faster than float64 and within about 1e-6 of
scikit-image's float64 result (the tests pin 1e-5; the contract is 1e-3).

PSNR (eq. 2): 10 log10(255^2 / MSE) over all RGB values; +inf for identical images.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

SSIM_SIGMA = 1.5
SSIM_TRUNCATE = 3.5
SSIM_RADIUS = int(SSIM_TRUNCATE * SSIM_SIGMA + 0.5)  # 5, as scipy.ndimage computes it
SSIM_WINDOW = 2 * SSIM_RADIUS + 1  # 11
SSIM_K1 = 0.01
SSIM_K2 = 0.03
DATA_RANGE = 255.0
LUMA_WEIGHTS = (0.299, 0.587, 0.114)
_CLEAN_STD_FLOOR = 1e-6


def _gaussian_kernel() -> np.ndarray:
    offsets = np.arange(-SSIM_RADIUS, SSIM_RADIUS + 1, dtype=np.float64)
    kernel = np.exp(-0.5 * (offsets / SSIM_SIGMA) ** 2)
    return kernel / kernel.sum()


_KERNEL = _gaussian_kernel()


def _check_rgb_pair(clean: np.ndarray, rainy: np.ndarray) -> None:
    for name, image in (("clean", clean), ("rainy", rainy)):
        if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
            got = f"{type(image).__name__} {getattr(image, 'shape', '')} {getattr(image, 'dtype', '')}".strip()
            raise ValueError(f"{name} must be an (H, W, 3) uint8 array, got {got}")
    if clean.shape != rainy.shape:
        raise ValueError(f"clean and rainy must have the same shape, got {clean.shape} and {rainy.shape}")


def luma(rgb: np.ndarray) -> np.ndarray:
    """BT.601 luma of an RGB image.

    Args:
        rgb: (H, W, 3) uint8 (or any real dtype), channels R, G, B.

    Returns:
        (H, W) float64 ``0.299 R + 0.587 G + 0.114 B``, not rounded.
    """
    image = rgb.astype(np.float64)
    return LUMA_WEIGHTS[0] * image[..., 0] + LUMA_WEIGHTS[1] * image[..., 1] + LUMA_WEIGHTS[2] * image[..., 2]


_KERNEL32 = _KERNEL.astype(np.float32)


def _filter(image: np.ndarray) -> np.ndarray:
    return cv2.sepFilter2D(image, cv2.CV_32F, _KERNEL32, _KERNEL32, borderType=cv2.BORDER_REFLECT)


def _luma32(rgb: np.ndarray) -> np.ndarray:
    # OpenCV's float RGB2GRAY is BT.601 (0.299, 0.587, 0.114) in float32: 3x faster than numpy.
    return cv2.cvtColor(rgb.astype(np.float32), cv2.COLOR_RGB2GRAY)


class _SsimMoments:
    """The rate-independent half of SSIM for a float32 gray image ``x`` (H, W): its local mean
    and variance and the constant terms, so that :meth:`mean_ssim` filters only ``y``."""

    def __init__(self, x: np.ndarray, data_range: float) -> None:
        self.x = x
        self.two_x = 2.0 * x
        self.mu_x = _filter(x)
        self.c1 = np.float32((SSIM_K1 * data_range) ** 2)
        self.c2 = np.float32((SSIM_K2 * data_range) ** 2)
        mu_x_sq = self.mu_x * self.mu_x
        self.two_mu_x = 2.0 * self.mu_x
        self.mu_x_sq_c1 = mu_x_sq + self.c1
        self.var_x_c2 = _filter(x * x) - mu_x_sq + self.c2

    def mean_ssim(self, y: np.ndarray) -> float:
        """Mean SSIM map of ``y`` (H, W) float32 against ``x``, the border cropped."""
        mu_y = _filter(y)
        mu_y_sq = mu_y * mu_y
        # Doubling is exact in floating point, so 2 E[xy] - 2 mu_x mu_y is computed as
        # E[2x y] - (2 mu_x) mu_y: bit for bit 2 (E[xy] - mu_x mu_y), two array passes fewer.
        numerator = self.two_mu_x * mu_y
        cov_term = _filter(self.two_x * y)  # 2 E[xy]; becomes 2 cov + c2 below, in place
        cov_term -= numerator
        cov_term += self.c2
        numerator += self.c1
        numerator *= cov_term
        var_term = _filter(y * y)  # E[y^2]; becomes var_x + var_y + c2 below, in place
        var_term -= mu_y_sq
        var_term += self.var_x_c2
        mu_y_sq += self.mu_x_sq_c1
        mu_y_sq *= var_term  # the denominator
        numerator /= mu_y_sq
        pad = SSIM_RADIUS
        return float(numerator[pad:-pad, pad:-pad].mean(dtype=np.float64))


class SsimReference:
    """The clean image's half of SSIM (luma, local mean and second moment), computed once.

    ``SsimReference(clean).ssim(rainy)`` equals ``image_quality(clean, rainy)[0]``; a sweep of
    rates against one clean frame saves two of the five window filters per rate.

    Args:
        clean: (H, W, 3) uint8 RGB, H and W >= 11.
    """

    def __init__(self, clean: np.ndarray) -> None:
        _check_rgb_pair(clean, clean)
        if min(clean.shape[:2]) < SSIM_WINDOW:
            raise ValueError(f"SSIM needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW} pixels "
                             f"(11-tap window), got {clean.shape[1]}x{clean.shape[0]}")
        self.clean = clean
        self._moments = _SsimMoments(_luma32(clean), DATA_RANGE)

    def ssim(self, rainy: np.ndarray) -> float:
        """Mean SSIM of ``rainy`` (H, W, 3) uint8 against the reference."""
        _check_rgb_pair(self.clean, rainy)
        return self._moments.mean_ssim(_luma32(rainy))

    def quality(self, rainy: np.ndarray) -> tuple[float, float]:
        """(SSIM, PSNR) of ``rainy`` against the reference, as :func:`image_quality`."""
        return self.ssim(rainy), psnr(self.clean, rainy)


def ssim_gray(first: np.ndarray, second: np.ndarray, data_range: float = DATA_RANGE) -> float:
    """Mean SSIM of two single-channel images (the module's convention).

    Args:
        first, second: (H, W) real images (computed in float32), H and W >= 11.
        data_range: L in C1 = (K1 L)^2, C2 = (K2 L)^2.

    Returns:
        mean SSIM over the map with a 5-pixel border cropped.
    """
    if first.shape != second.shape or first.ndim != 2:
        raise ValueError(f"ssim_gray needs two 2-D images of equal shape, got {first.shape} and {second.shape}")
    if min(first.shape) < SSIM_WINDOW:
        raise ValueError(f"SSIM needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW} pixels (11-tap window), got {first.shape[1]}x{first.shape[0]}")
    x = np.ascontiguousarray(first, dtype=np.float32)
    y = np.ascontiguousarray(second, dtype=np.float32)
    return _SsimMoments(x, data_range).mean_ssim(y)


def psnr(clean: np.ndarray, rainy: np.ndarray) -> float:
    """PSNR in dB over all RGB values, data range 255; ``math.inf`` for identical images.

    Args:
        clean, rainy: (H, W, 3) uint8.
    """
    _check_rgb_pair(clean, rainy)
    return psnr_of_squared_error(cv2.norm(clean, rainy, cv2.NORM_L2SQR), clean.size)


def psnr_of_squared_error(squared_error_sum: float, values: int) -> float:
    """PSNR in dB of a sum of squared differences over ``values`` RGB values (an exact integer:
    the CPU and GPU paths give the same figure); ``math.inf`` when the sum is 0."""
    mse = float(squared_error_sum) / values
    if mse == 0.0:
        return math.inf
    return 10.0 * math.log10(DATA_RANGE * DATA_RANGE / mse)


def contrast_loss_of(std_rainy: float, std_clean: float) -> float:
    """``1 - std_rainy / std_clean`` clipped to [0, 1]; 0 for a flat box (``std_clean`` below
    1e-6: no contrast to lose). The standard deviations are of a box's BT.601 luma."""
    if std_clean < _CLEAN_STD_FLOOR:
        return 0.0
    return min(max(1.0 - std_rainy / std_clean, 0.0), 1.0)


def image_quality(clean: np.ndarray, rainy: np.ndarray) -> tuple[float, float]:
    """(SSIM, PSNR) of a rainy image against its clean render (module docstring convention).

    Args:
        clean, rainy: (H, W, 3) uint8 RGB images of the same shape, H and W >= 11.

    Returns:
        (ssim on BT.601 luma, psnr in dB on RGB; inf when identical).
    """
    _check_rgb_pair(clean, rainy)
    return SsimReference(clean).quality(rainy)


def box_pixel_ranges(boxes: np.ndarray, height: int, width: int) -> np.ndarray:
    """Integer pixel ranges of boxes in pixel-edge coordinates.

    A pixel (column i, row j) belongs to a box when its centre (i + 0.5, j + 0.5) lies in
    [x1, x2) x [y1, y2); the range is clipped to the image.

    Args:
        boxes: (M, 4) float x1, y1, x2, y2 in pixels (x2 = last column + 1 for integer boxes).
        height, width: image size.

    Returns:
        (M, 4) int64 col0, row0, col1, row1 (exclusive ends); empty when col1 <= col0 or row1 <= row0.
    """
    boxes64 = boxes.astype(np.float64)
    col0 = np.clip(np.ceil(boxes64[:, 0] - 0.5), 0, width)
    row0 = np.clip(np.ceil(boxes64[:, 1] - 0.5), 0, height)
    col1 = np.clip(np.ceil(boxes64[:, 2] - 0.5), 0, width)
    row1 = np.clip(np.ceil(boxes64[:, 3] - 0.5), 0, height)
    return np.stack([col0, row0, col1, row1], axis=1).astype(np.int64)


def box_rain_labels(clean: np.ndarray, rainy: np.ndarray, coverage: np.ndarray, boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-box rain statistics for detection labels.

    Definitions, over the pixels whose centres lie inside a box (see :func:`box_pixel_ranges`):

    * rain_coverage = mean of ``coverage`` (per-pixel drop/streak opacity);
    * contrast_loss = ``1 - std(Y_rainy) / std(Y_clean)``, clipped to [0, 1], with Y the
      BT.601 luma (float64) and std the population standard deviation; 0 when
      ``std(Y_clean) < 1e-6`` (a flat box has no contrast to lose).

    A box containing no pixel centre (degenerate or outside the image) gets 0 for both.
    ``BoxRainReference(clean, boxes).labels(rainy, coverage)`` gives the same numbers and
    computes the clean image's half once for many rainy images.

    Args:
        clean, rainy: (H, W, 3) uint8 images.
        coverage: (H, W) float32 in [0, 1] (``RainFrame.coverage``).
        boxes: (M, 4) float32 x1, y1, x2, y2 pixel-edge coordinates (x2 = last column + 1).

    Returns:
        (rain_coverage (M,) float32, contrast_loss (M,) float32).
    """
    _check_rgb_pair(clean, rainy)
    _check_coverage(coverage, *clean.shape[:2])
    return BoxRainReference(clean, boxes).labels(rainy, coverage)


def _check_coverage(coverage: np.ndarray, height: int, width: int) -> None:
    if not isinstance(coverage, np.ndarray) or coverage.shape != (height, width):
        raise ValueError(f"coverage must be an ({height}, {width}) array, got {getattr(coverage, 'shape', type(coverage).__name__)}")


class BoxRainReference:
    """The clean image's half of :func:`box_rain_labels` (each box's pixel range and clean luma
    standard deviation), computed once; a sweep of rates against one clean frame then measures
    only the rainy side of each box per rate.

    Args:
        clean: (H, W, 3) uint8 RGB.
        boxes: (M, 4) float x1, y1, x2, y2 pixel-edge coordinates (x2 = last column + 1).
    """

    def __init__(self, clean: np.ndarray, boxes: np.ndarray) -> None:
        _check_rgb_pair(clean, clean)
        self.clean = clean
        boxes_array = np.asarray(boxes)
        if boxes_array.size and (boxes_array.ndim != 2 or boxes_array.shape[1] != 4):
            raise ValueError(f"boxes must be an (M, 4) array of x1, y1, x2, y2, got shape {boxes_array.shape}")
        if boxes_array.size and not np.all(np.isfinite(boxes_array)):
            raise ValueError("boxes must be finite, got NaN or inf coordinates")
        height, width = clean.shape[:2]
        self.ranges = box_pixel_ranges(boxes_array, height, width) if boxes_array.size else np.zeros((0, 4), np.int64)
        # std(Y_clean) of each box with pixels, None for a box without any
        self.clean_std: list[float | None] = []
        for col0, row0, col1, row1 in self.ranges:
            empty = col1 <= col0 or row1 <= row0
            self.clean_std.append(None if empty else _box_luma_std(clean[row0:row1, col0:col1]))

    def labels(self, rainy: np.ndarray, coverage: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(rain_coverage (M,) float32, contrast_loss (M,) float32) of ``rainy`` (H, W, 3)
        uint8 with per-pixel opacity ``coverage`` (H, W) float32, as :func:`box_rain_labels`."""
        _check_rgb_pair(self.clean, rainy)
        _check_coverage(coverage, *rainy.shape[:2])
        rain_coverage = np.zeros(len(self.ranges), dtype=np.float32)
        contrast_loss = np.zeros(len(self.ranges), dtype=np.float32)
        for index, ((col0, row0, col1, row1), std_clean) in enumerate(zip(self.ranges, self.clean_std)):
            if std_clean is None:
                continue
            box_coverage = coverage[row0:row1, col0:col1]  # its mean as ndarray.mean(dtype=float64)
            rain_coverage[index] = np.float32(_sum64(box_coverage, axis=None, dtype=np.float64) / box_coverage.size)
            if std_clean < _CLEAN_STD_FLOOR:
                continue
            std_rainy = _box_luma_std(rainy[row0:row1, col0:col1])
            contrast_loss[index] = np.float32(contrast_loss_of(std_rainy, std_clean))
        return rain_coverage, contrast_loss


_LUMA_WEIGHTS64 = np.array(LUMA_WEIGHTS, dtype=np.float64)
_sum64 = np.add.reduce  # ndarray.mean's own sum, without its Python wrapper


def _box_luma_std(rgb: np.ndarray) -> float:
    """Population standard deviation of the float64 BT.601 luma of ``rgb`` (h, w, 3) uint8, a
    box's pixels, in two C calls (numpy's ``luma(...).std()`` takes 13 array operations, each
    holding the GIL; a frame's 10 boxes x 10 rates of labels went from 6.3 to 4.0 ms)."""
    _, std = cv2.meanStdDev(rgb @ _LUMA_WEIGHTS64)
    return float(std[0, 0])
