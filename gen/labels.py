"""Labels from segmentation renders: pure functions on arrays.

Boxes are float32 ``x1, y1, x2, y2`` in pixel-edge coordinates: a box covering columns 10..19
has ``x1 = 10, x2 = 20`` (``x2 = last column + 1``). Instance maps are (H, W) int32 with the
actor instance id per pixel and -1 where no actor is.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rainbench.store.labels import FrameLabels


@dataclass(frozen=True)
class LabelFilter:
    """Which visible actors become labels. Defaults are documented in docs/format.md.

    - ``min_box_height``: visible box height in pixels (KITTI's "easy" starts at 40 px at
      1242x375; 8 px keeps distant actors a detector at 640 px can still see);
    - ``min_visible_fraction``: visible pixels / unoccluded in-image pixels;
    - ``min_visible_pixels``: absolute visible pixel count.
    """

    min_box_height: float = 8.0
    min_visible_fraction: float = 0.10
    min_visible_pixels: int = 20

    def __post_init__(self) -> None:
        def number(value) -> bool:
            return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_)) \
                and math.isfinite(value)

        # NaN passed "< 0" and then dropped every label (each actor became an ignore region)
        if not (number(self.min_box_height) and self.min_box_height >= 0):
            raise ValueError(f"min_box_height: expected a finite number >= 0 px, got {self.min_box_height!r}")
        if not (number(self.min_visible_fraction) and 0.0 <= self.min_visible_fraction <= 1.0):
            raise ValueError(
                f"min_visible_fraction: expected a number in 0..1, got {self.min_visible_fraction!r}"
            )
        if isinstance(self.min_visible_pixels, (bool, np.bool_)) or not isinstance(
                self.min_visible_pixels, (int, np.integer)) or self.min_visible_pixels < 1:
            raise ValueError(f"min_visible_pixels: expected an integer >= 1, got {self.min_visible_pixels!r}")


def _check_instance_map(instance_map: np.ndarray, name: str) -> None:
    if instance_map.ndim != 2 or not np.issubdtype(instance_map.dtype, np.integer):
        raise ValueError(
            f"{name}: expected (H, W) integer instance ids, got {instance_map.shape} "
            f"{instance_map.dtype}"
        )


def tight_boxes(instance_map: np.ndarray, num_instances: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel counts and tight boxes of every instance id in ``[0, num_instances)``.

    instance_map: (H, W) int, -1 = none. Returns counts (K,) int64 and boxes (K, 4) float32
    xyxy pixel-edge (NaN rows for instances without pixels). Ids >= K are ignored.
    """
    _check_instance_map(instance_map, "instance_map")
    counts = np.zeros(num_instances, dtype=np.int64)
    boxes = np.full((num_instances, 4), np.nan, dtype=np.float32)
    ys, xs = np.nonzero((instance_map >= 0) & (instance_map < num_instances))
    if ys.size == 0:
        return counts, boxes
    ids = instance_map[ys, xs]
    order = np.argsort(ids, kind="stable")
    ids, ys, xs = ids[order], ys[order], xs[order]
    present, starts, per_id = np.unique(ids, return_index=True, return_counts=True)
    counts[present] = per_id
    boxes[present, 0] = np.minimum.reduceat(xs, starts)
    boxes[present, 1] = np.minimum.reduceat(ys, starts)
    boxes[present, 2] = np.maximum.reduceat(xs, starts) + 1
    boxes[present, 3] = np.maximum.reduceat(ys, starts) + 1
    return counts, boxes


def alone_statistics(
    alone_map: np.ndarray, origin: tuple[int, int], margins: tuple[int, int],
    image_size: tuple[int, int], num_instances: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unoccluded statistics from an actor-alone render on a padded canvas.

    The canvas extends the image by ``margins = (mx, my)`` pixels on each side (same focal
    length): image pixel (u, v) is canvas pixel (u + mx, v + my); ``image_size = (W, H)``.
    alone_map: (h, w) int instance ids (-1 = none) of a window of that canvas whose top-left
    pixel is canvas pixel ``origin = (x0, y0)``; it must hold every pixel of its actors.
    Returns (in_image_counts (K,) int64, total_counts (K,) int64, amodal_boxes (K, 4) float32
    xyxy in image pixels, clipped to the image; NaN when the actor has no pixel in the image).
    """
    _check_instance_map(alone_map, "alone_map")
    margin_x, margin_y = margins
    width, height = image_size
    x0, y0 = origin
    h, w = alone_map.shape
    if x0 < 0 or y0 < 0 or x0 + w > width + 2 * margin_x or y0 + h > height + 2 * margin_y:
        raise ValueError(
            f"alone_map: expected a window inside the {width + 2 * margin_x}x"
            f"{height + 2 * margin_y} canvas, got {w}x{h} at {origin}")
    total = np.bincount(alone_map[alone_map >= 0].ravel(), minlength=num_instances)[:num_instances]
    # The image part of the window, in window coordinates.
    u0, v0 = max(0, margin_x - x0), max(0, margin_y - y0)
    u1, v1 = min(w, margin_x + width - x0), min(h, margin_y + height - y0)
    in_image = np.zeros(num_instances, np.int64)
    amodal = np.full((num_instances, 4), np.nan, np.float32)
    if u0 < u1 and v0 < v1:
        in_image, amodal = tight_boxes(alone_map[v0:v1, u0:u1], num_instances)
        amodal += np.array([x0 + u0 - margin_x, y0 + v0 - margin_y] * 2, np.float32)
    return in_image, total.astype(np.int64), amodal


def make_labels(
    visible_counts: np.ndarray,
    visible_boxes: np.ndarray,
    alone_in_image: np.ndarray,
    alone_total: np.ndarray,
    amodal_boxes: np.ndarray,
    class_of_instance: np.ndarray,
    label_filter: LabelFilter,
) -> FrameLabels:
    """Combine visible and unoccluded statistics into filtered labels, and the ignore regions
    of the visible actors the filter leaves out (:class:`FrameLabels`).

    All inputs are indexed by instance id (K,): counts int, boxes (K, 4) xyxy, classes int.
    visible_fraction = visible pixels / unoccluded in-image pixels (occlusion only, clipped to 1);
    truncation = unoccluded pixels outside the image / all unoccluded pixels on the padded canvas
    (projections reaching beyond the canvas margin are counted up to the margin).
    """
    num = class_of_instance.shape[0]
    for name, array in (("visible_counts", visible_counts), ("alone_in_image", alone_in_image),
                        ("alone_total", alone_total)):
        if array.shape != (num,):
            raise ValueError(f"{name}: expected shape ({num},), got {array.shape}")
    for name, array in (("visible_boxes", visible_boxes), ("amodal_boxes", amodal_boxes)):
        if array.shape != (num, 4):
            raise ValueError(f"{name}: expected shape ({num}, 4), got {array.shape}")
    with np.errstate(divide="ignore", invalid="ignore"):
        visible_fraction = np.where(
            alone_in_image > 0, np.minimum(1.0, visible_counts / np.maximum(alone_in_image, 1)), 0.0
        )
        truncation = np.where(
            alone_total > 0, 1.0 - alone_in_image / np.maximum(alone_total, 1), 0.0
        )
    height = visible_boxes[:, 3] - visible_boxes[:, 1]
    keep = (
        (visible_counts >= label_filter.min_visible_pixels)
        & (np.nan_to_num(height, nan=0.0) >= label_filter.min_box_height)
        & (visible_fraction >= label_filter.min_visible_fraction)
    )
    ids = np.flatnonzero(keep)
    # An amodal box always contains the visible box (rasterisation of the padded view can
    # differ from the main view by an edge pixel).
    amodal = _enclosing(amodal_boxes[ids], visible_boxes[ids])
    visible = visible_boxes[ids]
    ignored = np.flatnonzero(~keep & (visible_counts > 0))
    return FrameLabels(
        bbox=visible.astype(np.float32),
        bbox_amodal=amodal.astype(np.float32),
        class_id=class_of_instance[ids].astype(np.int32),
        instance_id=ids.astype(np.int32),
        visible_fraction=visible_fraction[ids].astype(np.float32),
        truncation=np.clip(truncation[ids], 0.0, 1.0).astype(np.float32),
        ignore_bbox=_enclosing(amodal_boxes[ignored], visible_boxes[ignored]).astype(np.float32),
        ignore_class_id=class_of_instance[ignored].astype(np.int32),
        ignore_instance_id=ignored.astype(np.int32),
    )


def _enclosing(amodal: np.ndarray, visible: np.ndarray) -> np.ndarray:
    """(N, 4) xyxy boxes enclosing each amodal box (NaN rows allowed) and its visible box."""
    enclosing = amodal.copy()
    enclosing[:, :2] = np.fmin(amodal[:, :2], visible[:, :2])
    enclosing[:, 2:] = np.fmax(amodal[:, 2:], visible[:, 2:])
    return enclosing


def group_disjoint(boxes: dict[int, tuple[float, float, float, float]]) -> list[list[int]]:
    """Greedy grouping of instance ids whose boxes (xyxy) do not overlap, in id order.

    Actors in one group can be rendered together "alone": none can hide another.
    """
    groups: list[list[int]] = []
    group_boxes: list[list[tuple[float, float, float, float]]] = []
    for instance in sorted(boxes):
        box = boxes[instance]
        for members, member_boxes in zip(groups, group_boxes):
            if all(box[2] <= b[0] or b[2] <= box[0] or box[3] <= b[1] or b[3] <= box[1]
                   for b in member_boxes):
                members.append(instance)
                member_boxes.append(box)
                break
        else:
            groups.append([instance])
            group_boxes.append([box])
    return groups


def union_window(boxes, canvas_size: tuple[int, int]) -> tuple[int, int, int, int]:
    """Integer window (x0, y0, x1, y1) covering every xyxy box, clipped to ``canvas_size``."""
    array = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    width, height = canvas_size
    x0 = int(np.clip(np.floor(array[:, 0].min()), 0, width - 1))
    y0 = int(np.clip(np.floor(array[:, 1].min()), 0, height - 1))
    x1 = int(np.clip(np.ceil(array[:, 2].max()), x0 + 1, width))
    y1 = int(np.clip(np.ceil(array[:, 3].max()), y0 + 1, height))
    return x0, y0, x1, y1
