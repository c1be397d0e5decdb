"""Tiny shards with known labels, written by the real ShardWriter (no rendering)."""

import dataclasses
import json

import numpy as np

from rainbench.store.labels import FrameLabels
from rainbench.store.shard import ShardWriter, shard_name
from rainbench.store.classes import CLASS_NAMES

OLD_CLASS_NAMES = ["person", "bicycle", "car", "motorcycle"]
"""The ``class_names`` attribute of shards written before bus and truck existed."""


def write_labelled_shard(folder, frames, *, scene_seed=0, frame_offset=0, width=100, height=80,
                         rates=(0.0,), class_names=CLASS_NAMES, attrs=None, ignore=None):
    """Write ``folder/scene{seed}_f{offset}.h5`` and return its path.

    ``frames``: one list per frame of ``(class_id, instance_id, (x1, y1, x2, y2), visible_fraction,
    truncation)`` labels. Images are grey with each box's outline drawn (the same at every rate).
    ``ignore``: one list per frame of ``(class_id, instance_id, (x1, y1, x2, y2))`` ignore regions
    (none when None).
    """
    rates = np.asarray(rates, np.float32)
    all_attrs = {"class_names": json.dumps(list(class_names)), "scene_seed": scene_seed,
                 "frame_offset": frame_offset, "fps": 10.0}
    all_attrs.update(attrs or {})
    path = folder / shard_name(scene_seed, frame_offset)
    folder.mkdir(parents=True, exist_ok=True)
    with ShardWriter(path, attrs=all_attrs, rates=rates, num_frames=len(frames), width=width, height=height,
                     K=np.eye(3), threads=1) as writer:
        for index, labels in enumerate(frames):
            boxes = np.array([box for _, _, box, _, _ in labels], np.float32).reshape(-1, 4)
            image = np.full((height, width, 3), 90, np.uint8)
            for x1, y1, x2, y2 in boxes.astype(int):
                image[y1:y2, x1] = image[y1:y2, x2 - 1] = image[y1, x1:x2] = image[y2 - 1, x1:x2] = 250
            frame_labels = FrameLabels(
                bbox=boxes, bbox_amodal=boxes.copy(),
                class_id=np.array([c for c, *_ in labels], np.int32),
                instance_id=np.array([i for _, i, *_ in labels], np.int32),
                visible_fraction=np.array([v for *_, v, _ in labels], np.float32),
                truncation=np.array([t for *_, t in labels], np.float32))
            if ignore is not None:
                regions = ignore[index]
                frame_labels = dataclasses.replace(
                    frame_labels,
                    ignore_bbox=np.array([box for *_, box in regions], np.float32).reshape(-1, 4),
                    ignore_class_id=np.array([c for c, *_ in regions], np.int32),
                    ignore_instance_id=np.array([i for _, i, _ in regions], np.int32))
            writer.write_frame(index, np.repeat(image[None], len(rates), axis=0), frame_labels, np.eye(4))
        writer.commit()
    return path
