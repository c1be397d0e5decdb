"""The per-rate statistics of :mod:`rainbench.rain.metrics`, batched over a frame's rates on a
torch device (a CUDA GPU in practice; the tests run the same code on the CPU).

:class:`TorchRateStatistics` takes one frame's clean image, its rainy images (one per rate > 0)
and their rain opacity, and returns the SSIM, PSNR and per-box rain labels of every rate in one
call: the images go to the device once and every filter runs over all rates at once. The
conventions are those of :mod:`rainbench.rain.metrics` (its module docstring); the numbers agree
with its NumPy/OpenCV path to float32 rounding (SSIM within 1e-5, box labels within 1e-5, PSNR
exactly), not byte for byte, so the device is part of a dataset's config.

* SSIM: the separable 11-tap Gaussian window as two matrix products with banded (H, H) and
  (W, W) matrices that hold the window and OpenCV's ``BORDER_REFLECT`` border, in float32.
  cuBLAS's float32 matrix product is deterministic for a given device and shape, and it runs at
  full float32 precision unless the process allowed TF32 (``torch.set_float32_matmul_precision``
  other than ``"highest"``), which :class:`TorchRateStatistics` refuses.
* PSNR: the squared differences summed as integers (int64), as OpenCV's ``NORM_L2SQR`` does in
  double: the same figure as the CPU path.
* Box labels: each box's pixels sliced out of all rates at once; standard deviations and means
  in float64, as :class:`~rainbench.rain.metrics.BoxRainReference`.

Importing this module imports torch (about a second): the generator imports it only when a
dataset's ``stats_device`` is not ``"cpu"``.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from rainbench.rain.metrics import (_KERNEL, DATA_RANGE, LUMA_WEIGHTS, SSIM_K1, SSIM_K2,
                                    SSIM_RADIUS, SSIM_WINDOW, _check_coverage, box_pixel_ranges,
                                    contrast_loss_of, psnr_of_squared_error)


def cuda_device_problem(device: torch.device, cpu_hint: str) -> str | None:
    """Why ``device`` cannot run here (``cpu_hint`` appended when there is no CUDA at all), or
    None (a CPU device, or a CUDA device this machine has)."""
    if device.type != "cuda":
        return None
    if not torch.cuda.is_available():
        return f"CUDA is not available on this machine (torch.cuda.is_available() is False); {cpu_hint}"
    if (device.index or 0) >= torch.cuda.device_count():
        return f"this machine has {torch.cuda.device_count()} CUDA device(s)"
    return None


def _window_matrix(size: int) -> np.ndarray:
    """(size, size) float64 M with ``M @ v`` = the Gaussian window applied to ``v`` (size,)
    with OpenCV's ``BORDER_REFLECT`` border (``fedcba|abcdef|fedcba``)."""
    matrix = np.zeros((size, size), np.float64)
    for row in range(size):
        for tap, weight in enumerate(_KERNEL):
            source = row + tap - SSIM_RADIUS
            if source < 0:
                source = -source - 1
            elif source >= size:
                source = 2 * size - source - 1
            matrix[row, source] += weight
    return matrix


class TorchRateStatistics:
    """SSIM, PSNR and per-box rain labels of one frame's rainy images, all rates in one batch.

    Args:
        device: a torch device (``"cuda"``, ``"cuda:1"``; ``"cpu"`` runs the same code on the
            CPU, which the tests use as the GPU path's twin).
        height, width: the images' size, both >= 11.

    Raises:
        ValueError: a CUDA device without CUDA or beyond the machine's devices, an image smaller
            than the window, or a process whose float32 matrix products may use TF32
            (``torch.get_float32_matmul_precision()`` must be ``"highest"``).

    Safe to call from several threads at once: it keeps no state between calls beyond the
    window matrices, which it never changes.
    """

    def __init__(self, device: str | torch.device, height: int, width: int) -> None:
        self.device = torch.device(device)
        problem = cuda_device_problem(self.device, "use cpu")
        if problem is not None:
            raise ValueError(f"stats_device {device}: {problem}")
        if min(height, width) < SSIM_WINDOW:
            raise ValueError(f"SSIM needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW} pixels "
                             f"(11-tap window), got {width}x{height}")
        if torch.get_float32_matmul_precision() != "highest":
            raise ValueError("stats_device: float32 matrix products must run at full precision; "
                             "this process set torch.set_float32_matmul_precision("
                             f"{torch.get_float32_matmul_precision()!r}), expected 'highest'")
        self.height, self.width = height, width
        self._rows = torch.as_tensor(_window_matrix(height), dtype=torch.float32, device=self.device)
        self._columns_t = torch.as_tensor(_window_matrix(width).T.copy(), dtype=torch.float32,
                                          device=self.device)
        self._luma_weights = torch.tensor(LUMA_WEIGHTS, dtype=torch.float64, device=self.device)
        self._luma_weights32 = self._luma_weights.to(torch.float32)

    def _filter(self, images: torch.Tensor) -> torch.Tensor:
        """The Gaussian window over (B, H, W) float32 images."""
        return torch.matmul(torch.matmul(self._rows, images), self._columns_t)

    def _to_device(self, images: Sequence[np.ndarray]) -> torch.Tensor:
        """(B, H, W, 3) uint8 on the device, from B (H, W, 3) uint8 arrays."""
        for image in images:
            if not (isinstance(image, np.ndarray) and image.dtype == np.uint8
                    and image.shape == (self.height, self.width, 3)):
                got = f"{type(image).__name__} {getattr(image, 'shape', '')} {getattr(image, 'dtype', '')}".strip()
                raise ValueError(f"expected ({self.height}, {self.width}, 3) uint8 images, got {got}")
        return torch.stack([torch.from_numpy(np.ascontiguousarray(image)).to(self.device)
                            for image in images])

    def mean_ssim(self, clean: torch.Tensor, rainy: torch.Tensor) -> torch.Tensor:
        """(B,) float64 mean SSIM of each of ``rainy`` (B, H, W, 3) uint8 against ``clean``
        (H, W, 3) uint8, both on the device; the border of :data:`SSIM_RADIUS` cropped."""
        x = (clean.to(torch.float32) * self._luma_weights32).sum(dim=-1)  # (H, W)
        y = (rainy.to(torch.float32) * self._luma_weights32).sum(dim=-1)  # (B, H, W)
        c1 = (SSIM_K1 * DATA_RANGE) ** 2
        c2 = (SSIM_K2 * DATA_RANGE) ** 2
        mu_x, x_sq = self._filter(torch.stack([x, x * x]))
        count = y.shape[0]
        mu_y, xy, y_sq = self._filter(torch.cat([y, x * y, y * y])).split(count)
        mu_x_mu_y = mu_x * mu_y
        mu_y_sq = mu_y * mu_y
        mu_x_sq = mu_x * mu_x
        numerator = (2.0 * mu_x_mu_y + c1) * (2.0 * (xy - mu_x_mu_y) + c2)
        denominator = (mu_x_sq + mu_y_sq + c1) * ((x_sq - mu_x_sq) + (y_sq - mu_y_sq) + c2)
        pad = SSIM_RADIUS
        ratio = (numerator / denominator)[:, pad:-pad, pad:-pad]
        return ratio.to(torch.float64).mean(dim=(1, 2))

    def frame(self, clean: np.ndarray, rainy: Sequence[np.ndarray], coverage: Sequence[np.ndarray],
              boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every statistic of one frame's rainy images.

        Args:
            clean: (H, W, 3) uint8 RGB, the frame's clean image.
            rainy: R arrays (H, W, 3) uint8 RGB, one per rate > 0.
            coverage: R arrays (H, W) float32 in [0, 1], each rainy image's rain opacity.
            boxes: (M, 4) float x1, y1, x2, y2 pixel-edge coordinates (x2 = last column + 1).

        Returns:
            (ssim (R,) float32, psnr (R,) float32 dB (inf where identical),
            rain_coverage (R, M) float32, contrast_loss (R, M) float32), each row as
            :class:`~rainbench.rain.metrics.SsimReference` and
            :class:`~rainbench.rain.metrics.BoxRainReference` define it.
        """
        count = len(rainy)
        if len(coverage) != count:
            raise ValueError(f"expected one coverage map per rainy image ({count}), got {len(coverage)}")
        boxes_array = np.asarray(boxes, np.float64).reshape(-1, 4)
        ssim = np.ones(count, np.float32)
        psnr = np.full(count, np.inf, np.float32)
        rain_coverage = np.zeros((count, len(boxes_array)), np.float32)
        contrast_loss = np.zeros((count, len(boxes_array)), np.float32)
        if count == 0:
            return ssim, psnr, rain_coverage, contrast_loss
        for opacity in coverage:
            _check_coverage(opacity, self.height, self.width)
        with torch.inference_mode():
            images = self._to_device([clean, *rainy])  # row 0: the clean image
            clean_image, rainy_images = images[0], images[1:]
            ssim_values = self.mean_ssim(clean_image, rainy_images)
            difference = rainy_images.to(torch.int32) - clean_image.to(torch.int32)
            squared_sums = (difference * difference).flatten(1).sum(dim=1, dtype=torch.int64)
            ranges = box_pixel_ranges(boxes_array, self.height, self.width) if len(boxes_array) \
                else np.zeros((0, 4), np.int64)
            kept = [index for index, (col0, row0, col1, row1) in enumerate(ranges)
                    if col1 > col0 and row1 > row0]
            stds = means = None
            if kept:
                opacity = torch.stack([torch.from_numpy(np.ascontiguousarray(o, np.float32)).to(self.device)
                                       for o in coverage])
                luma = (images.to(torch.float64) * self._luma_weights).sum(dim=-1)  # (1 + R, H, W)
                std_rows, mean_rows = [], []
                for index in kept:
                    col0, row0, col1, row1 = (int(v) for v in ranges[index])
                    std_rows.append(luma[:, row0:row1, col0:col1].flatten(1).std(dim=1, correction=0))
                    mean_rows.append(opacity[:, row0:row1, col0:col1].flatten(1)
                                     .mean(dim=1, dtype=torch.float64))
                stds = torch.stack(std_rows, dim=1).cpu().numpy()  # (1 + R, K)
                means = torch.stack(mean_rows, dim=1).cpu().numpy()  # (R, K)
            ssim_host = ssim_values.cpu().numpy()
            squared_host = squared_sums.cpu().numpy()
        for row in range(count):
            ssim[row] = np.float32(ssim_host[row])
            psnr[row] = np.float32(psnr_of_squared_error(int(squared_host[row]), clean.size))
        for column, index in enumerate(kept):
            rain_coverage[:, index] = means[:, column].astype(np.float32)
            for row in range(count):
                contrast_loss[row, index] = np.float32(
                    contrast_loss_of(float(stds[row + 1, column]), float(stds[0, column])))
        return ssim, psnr, rain_coverage, contrast_loss
