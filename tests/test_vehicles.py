"""Procedural mesh vehicles on tiny inline scenes whose answers are known from projection math."""

import dataclasses
import math

from rainbench.gl import mujoco  # imported once the GL backend is chosen
import numpy as np
import pytest

from rainbench.gen import labels as lb
from rainbench.gen.render import FrameRenderer
from rainbench.mjcf import vehicles as V
from rainbench.mjcf.scene import (_camera_quat, geom_instance_table, horizontal_to_vertical_fov,
                                  padded_size)

W, H = 200, 150
PREFIX = "actor000/"
SIDE_VIEW_M = 4.0  # orthographic side view: metres per image height for cars (x 2.6 bus/truck)
CAR_STYLES = ("sedan", "hatchback", "suv", "van", "pickup")


def _spec(shape: V.VehicleShape, view_height: float = SIDE_VIEW_M) -> mujoco.MjSpec:
    """Ground plane, a light, an orthographic side camera ("side", from -y, centred on the
    vehicle's box), a 3/4 perspective camera ("ego") and the vehicle at the origin."""
    spec = mujoco.MjSpec()
    spec.stat.extent = 100.0
    spec.visual.map.znear = 0.001
    spec.visual.map.zfar = 10.0
    spec.visual.quality.offsamples = 0
    spec.visual.global_.offwidth, spec.visual.global_.offheight = padded_size(W, H)[:2]
    spec.worldbody.add_geom(name="scenery/ground", type=mujoco.mjtGeom.mjGEOM_PLANE,
                            size=[60, 60, 0.1], rgba=[0.3, 0.3, 0.3, 1])
    spec.worldbody.add_light(name="sun", type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL,
                             dir=[-0.3, 0.4, -1.0])
    # Side camera looking along +y: image right = +x, image up = +z.
    side_quat = np.zeros(4)
    mujoco.mju_mat2Quat(side_quat, np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]).ravel())
    spec.worldbody.add_camera(name="side", pos=[0.0, -40.0, shape.height / 2],
                              quat=side_quat.tolist(), fovy=view_height,
                              proj=mujoco.mjtProjection.mjPROJ_ORTHOGRAPHIC)
    # Ego camera 3/4 front-left of the vehicle, looking back at it along -x rotated 30 deg.
    yaw = math.radians(180 + 30)
    ego = spec.worldbody.add_body(name="ego", mocap=True,
                                  pos=[1.1 * shape.length + 3.0, 0.75 * shape.length + 1.5, 0.0],
                                  quat=[math.cos(yaw / 2), 0, 0, math.sin(yaw / 2)])
    ego.add_camera(name="ego", pos=[0, 0, 1.5], quat=_camera_quat(),
                   fovy=horizontal_to_vertical_fov(60.0, W, H))
    body = spec.worldbody.add_body(name="vehicle", mocap=True)
    V.add_vehicle(spec, body, PREFIX, shape, (0.7, 0.1, 0.1))
    return spec


def _shape(style: str, seed: int = 3) -> V.VehicleShape:
    return V.sample_vehicle(style, np.random.default_rng(seed))


def _view_height(shape: V.VehicleShape) -> float:
    return SIDE_VIEW_M * (2.6 if shape.style in ("bus", "truck") else 1.0)


def _vehicle_geoms(model: mujoco.MjModel) -> np.ndarray:
    return np.array([i for i in range(model.ngeom) if model.geom(i).name.startswith(PREFIX)])


def _segmentation_mask(model: mujoco.MjModel, camera: str) -> np.ndarray:
    """(H, W) bool: pixels whose segmentation geom id is one of the vehicle's geoms."""
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    with mujoco.Renderer(model, H, W) as renderer:
        renderer.enable_segmentation_rendering()
        renderer.update_scene(data, camera)
        seg = renderer.render()
    is_geom = seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM)
    return is_geom & np.isin(seg[..., 0], _vehicle_geoms(model))


@pytest.fixture(scope="module")
def side_views():
    """style -> (shape, side-view mask (H, W) bool, metres per pixel)."""
    views = {}
    for style in V.VEHICLE_STYLES:
        shape = _shape(style)
        model = _spec(shape, _view_height(shape)).compile()
        views[style] = (shape, _segmentation_mask(model, "side"), _view_height(shape) / H)
    return views


def _welded(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Faces re-indexed onto unique vertex positions (the spec splits vertices at creases)."""
    _, index = np.unique(np.round(verts, 9), axis=0, return_inverse=True)
    return index.ravel()[faces]


def _closed_and_consistent(faces: np.ndarray) -> bool:
    """Every directed edge occurs once and its reverse once: a closed surface whose faces all
    turn the same way."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    if (counts != 1).any():
        return False
    forward = {tuple(e) for e in unique.tolist()}
    return all((b, a) in forward for a, b in forward)


def _volume(verts: np.ndarray, faces: np.ndarray) -> float:
    a, b, c = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def _spec_mesh(spec: mujoco.MjSpec, name: str) -> tuple[np.ndarray, np.ndarray]:
    mesh = spec.mesh(name)
    return (np.asarray(mesh.uservert).reshape(-1, 3),
            np.asarray(mesh.userface, dtype=np.int64).reshape(-1, 3))


@pytest.mark.parametrize("style", V.VEHICLE_STYLES)
def test_every_style_compiles_exports_and_reloads(style):
    spec = _spec(_shape(style))
    model = spec.compile()
    reloaded = mujoco.MjModel.from_xml_string(spec.to_xml())
    assert reloaded.ngeom == model.ngeom and reloaded.nmesh == model.nmesh >= 2
    assert [reloaded.geom(i).name for i in range(reloaded.ngeom)] == [
        model.geom(i).name for i in range(model.ngeom)]
    np.testing.assert_allclose(reloaded.mesh_vert, model.mesh_vert, atol=1e-3)  # 6 digits
    # Every part is named under the prefix and never collides; the meshes are the actor's own.
    body = model.body("vehicle").id
    geoms = [i for i in range(model.ngeom) if model.geom_bodyid[i] == body]
    assert geoms and all(model.geom(i).name.startswith(PREFIX) for i in geoms)
    assert (model.geom_contype[geoms] == 0).all() and (model.geom_conaffinity[geoms] == 0).all()
    assert all(model.mesh(i).name.startswith(PREFIX) for i in range(model.nmesh))
    # A modest triangle budget for software rendering.
    assert model.mesh_facenum.sum() < 2000


def test_two_vehicles_share_a_spec_with_their_own_meshes():
    spec = _spec(_shape("sedan"))
    other = spec.worldbody.add_body(name="other", mocap=True, pos=[0, 6, 0])
    V.add_vehicle(spec, other, "actor001/", _shape("bus"), (0.9, 0.7, 0.1))
    model = mujoco.MjModel.from_xml_string(spec.to_xml())
    names = {model.mesh(i).name for i in range(model.nmesh)}
    assert {"actor000/shell", "actor000/glass", "actor000/screen", "actor001/shell",
            "actor001/glass", "actor001/screen"} <= names


@pytest.mark.parametrize("style", V.VEHICLE_STYLES)
def test_raked_screens_are_lighter_than_the_side_windows(style):
    """Windscreen and rear window mirror the sky (lighter), the side windows the street."""
    shape = _shape(style)
    meshes = V.vehicle_meshes(shape)
    screen = meshes["screen"]
    # the screens lie across the car (front and back), the side panes along its sides
    assert np.ptp(screen.verts[:, 1]) > 0.6 * shape.width
    if "glass" in meshes:
        assert np.abs(meshes["glass"].verts[:, 1]).min() > 0.3 * shape.width
    model = mujoco.MjModel.from_xml_string(_spec(shape).to_xml())
    rgba = {name: model.geom(f"{PREFIX}{name}").rgba for name in meshes
            if name in ("screen", "glass")}
    assert np.allclose(rgba["screen"], V.SCREEN_GLASS)
    assert rgba["screen"][:3].mean() > 1.3 * np.asarray(V.GLASS[:3]).mean()
    if "glass" in rgba:
        assert np.allclose(rgba["glass"], V.GLASS)


@pytest.mark.parametrize("style", V.VEHICLE_STYLES)
def test_side_silhouette_box_is_length_by_height(style, side_views):
    shape, mask, metres_per_px = side_views[style]
    instance = np.where(mask, 0, -1).astype(np.int32)
    counts, boxes = lb.tight_boxes(instance, 1)
    # Orthographic view centred on (x 0, z height / 2): the box spans x +-length/2, z 0..height;
    # a pixel is covered when its centre is, so each edge is within half a pixel (+ 0.5 slack).
    half_w, half_h = shape.length / 2 / metres_per_px, shape.height / 2 / metres_per_px
    expected = [W / 2 - half_w, H / 2 - half_h, W / 2 + half_w, H / 2 + half_h]
    np.testing.assert_allclose(boxes[0], expected, atol=1.0)
    # Hence the width / height ratio is length / height within the +-1 px of each side.
    width_px, height_px = boxes[0, 2] - boxes[0, 0], boxes[0, 3] - boxes[0, 1]
    length_px, tall_px = 2 * half_w, 2 * half_h
    ratio = width_px / height_px
    assert (length_px - 2) / (tall_px + 2) <= ratio <= (length_px + 2) / (tall_px - 2)
    # The silhouette fills most of its box (a body, not a frame of thin parts).
    assert counts[0] > 0.6 * width_px * height_px


def test_bus_and_truck_are_much_larger_than_a_sedan(side_views):
    area = {style: mask.sum() * metres_per_px**2
            for style, (_, mask, metres_per_px) in side_views.items()}
    assert 4.0 < area["sedan"] < 7.5  # m^2 of a 4.5-4.9 x 1.40-1.48 m side
    assert area["bus"] > 4 * area["sedan"] and area["truck"] > 3 * area["sedan"]
    assert area["hatchback"] < area["sedan"] < area["suv"] < area["van"]


@pytest.mark.parametrize("style", V.VEHICLE_STYLES)
def test_label_box_is_the_box_of_the_vehicle_geom_pixels(style):
    spec = _spec(_shape(style))
    model = spec.compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    table = geom_instance_table(model)
    assert (table[_vehicle_geoms(model)] == 0).all() and (table >= 0).sum() == len(
        _vehicle_geoms(model))
    with FrameRenderer(model, W, H, table) as renderer:
        renderer.update(data)
        instance, _ = renderer.render_instances()
    mask = _segmentation_mask(model, "ego")
    assert mask.sum() > 1000
    # The label pipeline's instance pixels are exactly the pixels of the vehicle's geoms...
    np.testing.assert_array_equal(instance == 0, mask)
    # ... so its label box is their tight box.
    counts, boxes = lb.tight_boxes(instance, 1)
    ys, xs = np.nonzero(mask)
    assert counts[0] == mask.sum()
    assert boxes[0].tolist() == [xs.min(), ys.min(), xs.max() + 1, ys.max() + 1]


# Shell volume / its bounding-box volume (seeds 0-7 give sedan 0.57-0.61, bus 0.87-0.91): the
# lower the more of the box the rounding, the arches and a narrower cabin above the belt leave
# empty; a truck's shell is its cab. A face turned inwards subtracts its share twice.
VOLUME_FRACTION = {"sedan": (0.52, 0.66), "hatchback": (0.58, 0.72), "suv": (0.62, 0.76),
                   "van": (0.70, 0.82), "pickup": (0.52, 0.66), "bus": (0.84, 0.95),
                   "truck": (0.76, 0.88)}


@pytest.mark.parametrize("style", V.VEHICLE_STYLES)
def test_meshes_are_closed_and_face_outwards(style):
    spec = _spec(_shape(style))
    model = spec.compile()  # exact mesh inertia: MuJoCo rejects inward-facing meshes
    for index in range(model.nmesh):
        name = model.mesh(index).name
        verts, faces = _spec_mesh(spec, name)
        assert _closed_and_consistent(_welded(verts, faces)), name
        volume = _volume(verts, faces)
        assert volume > 0, name
        # MuJoCo's compiled mesh (re-centred, re-oriented) encloses the same volume.
        start, count = model.mesh_vertadr[index], model.mesh_vertnum[index]
        fstart, fcount = model.mesh_faceadr[index], model.mesh_facenum[index]
        compiled = _volume(model.mesh_vert[start:start + count],
                           model.mesh_face[fstart:fstart + fcount])
        assert compiled == pytest.approx(volume, rel=1e-4), name
    verts, faces = _spec_mesh(spec, f"{PREFIX}shell")
    box = np.prod(verts.max(axis=0) - verts.min(axis=0))
    low, high = VOLUME_FRACTION[style]
    assert low < _volume(verts, faces) / box < high


def test_inverted_faces_are_caught():
    spec = _spec(_shape("sedan"))
    verts, faces = _spec_mesh(spec, f"{PREFIX}shell")
    welded = _welded(verts, faces)
    partly = welded.copy()
    partly[:40] = partly[:40, [0, 2, 1]]
    assert _closed_and_consistent(welded) and not _closed_and_consistent(partly)
    spec.mesh(f"{PREFIX}shell").userface = faces[:, [0, 2, 1]].ravel().tolist()
    with pytest.raises(ValueError, match="mesh volume is negative"):
        spec.compile()


def test_lamps_are_named_and_where_lamp_positions_says():
    for style in ("sedan", "truck"):
        shape = _shape(style)
        model = _spec(shape).compile()
        lamps = V.lamp_positions(shape)
        for kind, name in (("head", "headlight"), ("tail", "taillight")):
            for centre, tag in zip(lamps[kind], "lr"):
                np.testing.assert_allclose(model.geom(f"{PREFIX}{name}_{tag}").pos, centre,
                                           atol=1e-9)
        (head_l, head_r), (tail_l, tail_r) = lamps["head"], lamps["tail"]
        assert head_l[1] > 0 > head_r[1] and tail_l[1] > 0 > tail_r[1]  # left is +y
        assert head_l[0] > shape.length / 2 - 0.1 and tail_l[0] < -shape.length / 2 + 0.1
        assert 0.3 < head_l[2] < 1.2


def test_same_seed_same_xml_other_seed_other_sizes():
    def xml(seed, style="pickup"):
        return _spec(_shape(style, seed)).to_xml()

    assert xml(11) == xml(11)
    assert xml(11) != xml(12)
    lengths = {_shape("sedan", seed).length for seed in range(5)}
    assert len(lengths) == 5 and all(4.5 <= x <= 4.9 for x in lengths)
    assert all(10.0 <= _shape("bus", seed).length <= 12.0 for seed in range(5))
    assert all(7.0 <= _shape("truck", seed).length <= 9.0 for seed in range(5))


def test_classes_paints_and_bad_arguments():
    assert V.VEHICLE_CLASS == {"sedan": 2, "hatchback": 2, "suv": 2, "van": 2, "pickup": 2,
                               "bus": 5, "truck": 7}
    rng = np.random.default_rng(0)
    assert V.sample_paint("bus", rng) in V.BUS_PAINTS
    assert V.sample_paint("sedan", rng, palette=((0.1, 0.2, 0.3),)) == (0.1, 0.2, 0.3)
    with pytest.raises(ValueError, match=r"vehicle style: expected one of sedan, hatchback, "
                                         r"suv, van, pickup, bus, truck, got 'tram'"):
        V.sample_vehicle("tram", rng)
    spec = mujoco.MjSpec()
    shape = dataclasses.replace(_shape("van"), style="lorry")
    with pytest.raises(ValueError, match="vehicle style: expected one of .* got 'lorry'"):
        V.add_vehicle(spec, spec.worldbody, PREFIX, shape, (0.5, 0.5, 0.5))
    with pytest.raises(ValueError, match=r"paint: expected an rgb triple in 0..1, got \(2, 0, 0\)"):
        V.add_vehicle(spec, spec.worldbody, PREFIX, _shape("van"), (2, 0, 0))


@pytest.mark.parametrize("style", ["hatchback", "van", "truck"])
def test_requested_sizes_are_built_exactly_even_at_the_limits(style):
    (l_low, l_high), (w_low, w_high), (h_low, h_high) = V.SIZE_RANGES[style]
    slack = 1 - V.SIZE_SLACK, 1 + V.SIZE_SLACK
    for size in ((l_low * slack[0], w_high * slack[1], h_low * slack[0]),
                 (l_high * slack[1], w_low * slack[0], h_high * slack[1])):
        shape = V.sample_vehicle(style, np.random.default_rng(1), size=size)
        assert (shape.length, shape.width, shape.height) == size
        model = _spec(shape, _view_height(shape) * 1.2).compile()
        mask = _segmentation_mask(model, "side")
        _, boxes = lb.tight_boxes(np.where(mask, 0, -1).astype(np.int32), 1)
        px = _view_height(shape) * 1.2 / H  # metres per pixel
        assert (boxes[0, 2] - boxes[0, 0]) * px == pytest.approx(shape.length, abs=2 * px)
        assert (boxes[0, 3] - boxes[0, 1]) * px == pytest.approx(shape.height, abs=2 * px)
        verts, faces = _spec_mesh(_spec(shape), f"{PREFIX}shell")
        assert _closed_and_consistent(_welded(verts, faces)) and _volume(verts, faces) > 0
    # The same draws either way: only the size differs from the sampled shape.
    sampled = V.sample_vehicle(style, np.random.default_rng(1))
    sized = V.sample_vehicle(style, np.random.default_rng(1),
                             size=(sampled.length, sampled.width, sampled.height))
    assert sized == sampled
    with pytest.raises(ValueError, match=rf"size: expected a {style} length in .* m, got 1.0"):
        V.sample_vehicle(style, np.random.default_rng(1), size=(1.0, w_low, h_low))


def test_instance_ids_past_999_are_read_whole():
    """A long residential clip has over a thousand actors; reading three digits of
    ``actor1043/`` gave 104, a parked car's id: the clip's people, bicycles and motorcycle were
    labelled as that car."""
    spec = mujoco.MjSpec()
    for name in ("actor007/body", "actor100/body", "actor999/wheel", "actor1000/body", "actor1009/x",
                 "actor1043/rider", "actor12345/y", "scenery/road", "actorless"):
        spec.worldbody.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.1, 0, 0])
    table = geom_instance_table(spec.compile())
    assert table.tolist() == [7, 100, 999, 1000, 1009, 1043, 12345, -1, -1]
