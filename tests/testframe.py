"""A synthetic street frame with a consistent depth map, for tests and benchmarks of rain.

Not a renderer: a level pinhole camera 1.5 m above a flat road, sky above the horizon, two
building facades, a few fronto-parallel "vehicles" and a "pedestrian" box, with procedural
texture so that SSIM has structure to lose. Everything is drawn from an explicit generator.
"""

from __future__ import annotations

import cv2
import numpy as np

CAMERA_HEIGHT_M = 1.5
FACADE_OFFSET_M = (-7.0, 8.0)  # x of the left and right building fronts
FACADE_HEIGHT_M = 12.0
_OBJECTS = (
    # x_left, x_right (m), height above road (m), depth (m), RGB
    (-2.6, -0.8, 1.5, 12.0, (150, 30, 30)),
    (1.2, 3.0, 1.6, 24.0, (40, 60, 140)),
    (2.0, 4.0, 1.7, 6.5, (200, 200, 205)),
    (-3.4, -2.9, 1.8, 9.0, (80, 120, 60)),
)


def intrinsics(height: int, width: int, hfov_deg: float = 90.0) -> np.ndarray:
    """(3, 3) float64 pinhole intrinsics with square pixels and a centred principal point.

    Args:
        height, width: image size in pixels.
        hfov_deg: horizontal field of view in degrees (CARLA's default camera is 90).
    """
    fx = 0.5 * width / np.tan(np.radians(hfov_deg) / 2.0)
    return np.array([[fx, 0.0, width / 2.0], [0.0, fx, height / 2.0], [0.0, 0.0, 1.0]], dtype=np.float64)


def _smooth_noise(rng: np.random.Generator, height: int, width: int, sigma: float) -> np.ndarray:
    noise = rng.standard_normal((height, width)).astype(np.float32)
    smooth = cv2.GaussianBlur(noise, (0, 0), sigma)
    return smooth / max(float(smooth.std()), 1e-6)


def street_frame(rng: np.random.Generator, height: int = 600, width: int = 800, hfov_deg: float = 90.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A street scene.

    Args:
        rng: generator for the textures.
        height, width: image size in pixels.
        hfov_deg: horizontal field of view in degrees.

    Returns:
        (rgb (H, W, 3) uint8, depth (H, W) float32 metres along the optical axis with +inf for
        sky, K (3, 3) float64).
    """
    K = intrinsics(height, width, hfov_deg)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    u = (np.arange(width, dtype=np.float64) + 0.5 - cx) / fx  # X / Z per column
    v = (np.arange(height, dtype=np.float64) + 0.5 - cy) / fy  # Y / Z per row (Y down)
    ray_u = np.broadcast_to(u[None, :], (height, width))
    ray_v = np.broadcast_to(v[:, None], (height, width))

    depth = np.full((height, width), np.inf, dtype=np.float64)
    rgb = np.zeros((height, width, 3), dtype=np.float64)

    # sky: vertical gradient with soft clouds
    sky_t = np.clip((np.arange(height) / max(cy, 1.0)), 0, 1)[:, None, None]
    sky = (1 - sky_t) * np.array([120.0, 150.0, 200.0]) + sky_t * np.array([190.0, 200.0, 215.0])
    clouds = _smooth_noise(rng, height, width, 12.0 * width / 800)[..., None]
    rgb[:] = sky + 12.0 * clouds

    # road: y = camera height below the camera
    with np.errstate(divide="ignore"):
        road_z = np.where(ray_v > 1e-6, CAMERA_HEIGHT_M / np.maximum(ray_v, 1e-6), np.inf)
    road = np.isfinite(road_z) & (road_z < 400.0)
    depth[road] = road_z[road]
    with np.errstate(invalid="ignore"):
        road_x = ray_u * road_z
    asphalt = 85.0 + 10.0 * _smooth_noise(rng, height, width, 1.0) + 8.0 * _smooth_noise(rng, height, width, 6.0)
    with np.errstate(invalid="ignore"):  # inf depths (sky rows) give NaN, which compares False
        lane = (np.abs(np.abs(road_x) - 1.75) < 0.08) & (np.mod(road_z, 9.0) < 4.5)
        edge = np.abs(np.abs(road_x - 0.5) - 5.0) < 0.1
    paint = (lane | edge) & road
    road_rgb = np.stack([asphalt, asphalt, asphalt * 1.04], axis=-1)
    road_rgb[paint] = 225.0
    rgb[road] = road_rgb[road]

    # facades: planes x = const, from the road up to FACADE_HEIGHT_M
    window_noise = _smooth_noise(rng, height, width, 2.0)
    for facade_x, base in zip(FACADE_OFFSET_M, ((170.0, 140.0, 110.0), (120.0, 125.0, 135.0))):
        with np.errstate(divide="ignore", invalid="ignore"):
            facade_z = np.where(ray_u * facade_x > 0, facade_x / ray_u, np.inf)
        with np.errstate(invalid="ignore"):  # inf * 0 and mod(inf) give NaN, which compares False
            world_y = ray_v * facade_z  # down from the camera
            hit = np.isfinite(facade_z) & (world_y < CAMERA_HEIGHT_M) & (world_y > CAMERA_HEIGHT_M - FACADE_HEIGHT_M) & (facade_z < depth) & (facade_z > 0.5)
            windows = (np.mod(facade_z, 4.0) < 2.2) & (np.mod(world_y, 3.0) < 1.6) & (world_y < -0.5)
        colour = np.array(base) + 10.0 * window_noise[..., None]
        colour = np.where(windows[..., None], np.array([60.0, 70.0, 85.0]) + 25.0 * window_noise[..., None], colour)
        depth = np.where(hit, facade_z, depth)
        rgb = np.where(hit[..., None], colour, rgb)

    # vehicles / pedestrian: fronto-parallel boxes standing on the road
    for x_left, x_right, box_height, box_z, colour in _OBJECTS:
        col0 = int(np.clip(np.floor(cx + fx * x_left / box_z), 0, width))
        col1 = int(np.clip(np.ceil(cx + fx * x_right / box_z), 0, width))
        row1 = int(np.clip(np.ceil(cy + fy * CAMERA_HEIGHT_M / box_z), 0, height))
        row0 = int(np.clip(np.floor(cy + fy * (CAMERA_HEIGHT_M - box_height) / box_z), 0, height))
        if col1 <= col0 or row1 <= row0:
            continue
        region = (slice(row0, row1), slice(col0, col1))
        nearer = depth[region] > box_z
        patch = np.array(colour, dtype=np.float64) + 6.0 * window_noise[region][..., None]
        glass_rows = slice(0, max(1, (row1 - row0) * 2 // 5))
        patch[glass_rows] = 0.45 * patch[glass_rows] + 20.0
        rgb[region] = np.where(nearer[..., None], patch, rgb[region])
        depth[region] = np.where(nearer, box_z, depth[region])

    rgb = cv2.GaussianBlur(np.clip(rgb, 0, 255).astype(np.float32), (0, 0), 0.6)
    return np.clip(np.rint(rgb), 0, 255).astype(np.uint8), depth.astype(np.float32), K
