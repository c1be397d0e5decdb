"""Shared fixtures. MuJoCo comes from ``rainbench.gl``, which chooses its GL backend (MUJOCO_GL)
before importing it."""

from rainbench.gl import mujoco  # imported once the GL backend is chosen
import numpy as np
import pytest

from rainbench.mjcf.scene import ACTOR_PREFIX, _camera_quat, horizontal_to_vertical_fov


def tiny_scene(boxes, width=160, height=120, camera_height=1.5, hfov=90.0):
    """A ground plane, an ego camera at (0, 0, camera_height) looking along +x, and box actors.

    ``boxes``: list of (centre xyz, half sizes xyz); box k is actor instance k.
    Returns the compiled model and its geom -> instance table.
    """
    spec = mujoco.MjSpec()
    spec.stat.extent = 100.0
    spec.visual.map.znear = 0.001
    spec.visual.map.zfar = 10.0
    spec.visual.quality.offsamples = 0
    spec.visual.global_.offwidth = width * 2
    spec.visual.global_.offheight = height * 2
    spec.worldbody.add_geom(name="scenery/ground", type=mujoco.mjtGeom.mjGEOM_PLANE,
                            size=[50, 50, 0.1], rgba=[0.3, 0.3, 0.3, 1])
    ego = spec.worldbody.add_body(name="ego", mocap=True)
    ego.add_camera(name="ego", pos=[0, 0, camera_height], quat=_camera_quat(),
                   fovy=horizontal_to_vertical_fov(hfov, width, height))
    for index, (centre, half) in enumerate(boxes):
        spec.worldbody.add_geom(name=ACTOR_PREFIX.format(index) + "box",
                                type=mujoco.mjtGeom.mjGEOM_BOX, size=list(half),
                                pos=list(centre), rgba=[0.8, 0.1, 0.1, 1])
    model = spec.compile()
    table = np.array([int(model.geom(i).name[5:8]) if model.geom(i).name.startswith("actor")
                      else -1 for i in range(model.ngeom)], dtype=np.int32)
    return model, table


def assert_same_detections(reference, other, top=5):
    """Each of the ``top`` best detections of ``reference`` has a twin in ``other``: the same
    class, every box edge within 1 px, the score within 2e-3."""
    ref_boxes, ref_scores, ref_ids = reference
    boxes, scores, ids = other
    assert len(ref_boxes) > top
    for index in np.argsort(-ref_scores)[:top]:
        distance = np.abs(boxes - ref_boxes[index]).max(axis=1) + 10 * (ids != ref_ids[index])
        twin = int(np.argmin(distance))
        assert distance[twin] < 1.0 and abs(scores[twin] - ref_scores[index]) < 2e-3


@pytest.fixture
def make_tiny_scene():
    return tiny_scene
