"""People, riders and their vehicles (mjcf/parts.py, mjcf/people.py) in tiny inline scenes whose
answers follow from the builds and the projection."""

import math

from rainbench.gl import mujoco  # imported once the GL backend is chosen
import numpy as np
import pytest

from rainbench.mjcf import layout as L
from rainbench.mjcf import parts
from rainbench.mjcf.scene import _camera_quat, geom_instance_table

COLOURS = {"shirt": (0.7, 0.1, 0.1), "trousers": (0.1, 0.2, 0.6), "skin": (0.87, 0.67, 0.53)}
W, H = 160, 120


def _spec(camera_pos, fovy_deg, camera_quat=None):
    """Ground, a light and a camera ``cam`` at ``camera_pos`` looking along +x (or turned by
    ``camera_quat``)."""
    spec = mujoco.MjSpec()
    spec.stat.extent = 100.0
    spec.visual.map.znear = 0.001
    spec.visual.map.zfar = 10.0
    spec.visual.global_.offwidth, spec.visual.global_.offheight = W, H
    spec.worldbody.add_geom(name="scenery/ground", type=mujoco.mjtGeom.mjGEOM_PLANE,
                            size=[60, 60, 0.1], rgba=[0.3, 0.3, 0.3, 1])
    spec.worldbody.add_light(name="sun", pos=[0, 0, 20], dir=[0, 0, -1])
    quat = _camera_quat() if camera_quat is None else list(camera_quat)
    spec.worldbody.add_camera(name="cam", pos=list(camera_pos), quat=quat, fovy=fovy_deg)
    return spec


def _pose(model, data, prefix, pose):
    for joint, angle in pose.items():
        data.qpos[model.joint(prefix + joint).qposadr[0]] = angle


def _segment(model, data):
    """(H, W) geom id of every pixel, -1 where no geom."""
    with mujoco.Renderer(model, H, W) as renderer:
        renderer.enable_segmentation_rendering()
        renderer.update_scene(data, camera="cam")
        seg = renderer.render()
    return np.where(seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM), seg[..., 0], -1)


def _geoms(model, prefix):
    return [g for g in range(model.ngeom) if model.geom(g).name.startswith(prefix)]


def _world_aabb(model, data, geoms):
    """(lo (3,), hi (3,)) world bounds of ``geoms`` after mj_forward."""
    lows, highs = [], []
    for g in geoms:
        rotation = data.geom_xmat[g].reshape(3, 3)
        centre = data.geom_xpos[g] + rotation @ model.geom_aabb[g, :3]
        half = np.abs(rotation) @ model.geom_aabb[g, 3:]
        lows.append(centre - half)
        highs.append(centre + half)
    return np.min(lows, axis=0), np.max(highs, axis=0)


def _rows(mask):
    rows = np.flatnonzero(mask.any(axis=1))
    return rows[0], rows[-1]


def test_child_renders_shorter_than_adult_by_the_height_ratio():
    """Side view from 20 m, 6 deg vertical FOV: near-orthographic, so pixel heights are
    f * height / 20 m (f = 60 px / tan 3 deg = 1145 px); depth spread of a body (+-0.15 m) moves
    them by < 1 %, pixel rounding by <= 2 px of ~65: the ratio is exact to 0.04."""
    spec = _spec((0.0, 0.0, 0.9), 6.0)
    adult, child = parts.PersonBuild(), parts.PersonBuild(height_m=1.1, girth=0.95)
    for prefix, build, y in (("actor000/", adult, 0.7), ("actor001/", child, -0.7)):
        body = spec.worldbody.add_body(name=prefix + "unit", pos=[20.0, y, 0.0])
        parts.add_person(body, prefix, COLOURS, build=build)
    model = spec.compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    heights = {}
    for prefix, build in (("actor000/", adult), ("actor001/", child)):
        top = _world_aabb(model, data, _geoms(model, prefix))[1][2]
        assert build.height_m <= top <= build.height_m + 0.03  # hair adds ~1 cm
        heights[prefix] = top
    seg = _segment(model, data)
    focal = (H / 2) / math.tan(math.radians(3.0))
    pixels = {}
    for prefix in heights:
        top_row, bottom_row = _rows(np.isin(seg, _geoms(model, prefix)))
        pixels[prefix] = bottom_row - top_row + 1
        assert pixels[prefix] == pytest.approx(focal * heights[prefix] / 20.0, abs=3)
    ratio = pixels["actor001/"] / pixels["actor000/"]
    assert ratio == pytest.approx(heights["actor001/"] / heights["actor000/"], abs=0.04)
    assert ratio < 0.7


def test_children_have_bigger_heads_and_shorter_legs_for_their_height():
    child = parts.body_proportions(parts.PersonBuild(height_m=1.1))
    adult = parts.body_proportions(parts.PersonBuild(height_m=1.8))
    assert child.head_height / child.height > 0.17 > 0.14 > adult.head_height / adult.height
    assert child.hip_z / child.height < 0.49 < 0.52 < adult.hip_z / adult.height
    assert parts.hip_height() == pytest.approx(0.93, abs=0.002)  # the old adult's hips


def _umbrella_scene(umbrella):
    spec = _spec((0.0, 0.0, 1.5), 40.0)
    body = spec.worldbody.add_body(name="walker", pos=[8.0, 0.0, 0.0])
    parts.add_person(body, "actor000/", COLOURS, build=parts.PersonBuild(1.7),
                     umbrella=umbrella)
    model = spec.compile()
    data = mujoco.MjData(model)
    pose = parts.walking_pose(1.0)
    pose.update(parts.UMBRELLA_ARM)
    _pose(model, data, "actor000/", pose)
    mujoco.mj_forward(model, data)
    return model, data


def test_umbrella_is_part_of_the_person_and_raises_the_box_top():
    model, data = _umbrella_scene((0.1, 0.2, 0.7))
    names = [model.geom(g).name for g in range(model.ngeom)]
    assert {"actor000/umbrella_canopy", "actor000/umbrella_shaft"} <= set(names)
    seg = _segment(model, data)
    instance = geom_instance_table(model)
    labels = np.where(seg >= 0, instance[np.maximum(seg, 0)], -1)
    umbrella = np.isin(seg, [model.geom(n).id for n in names if "umbrella" in n])
    assert umbrella.sum() > 50 and (labels[umbrella] == 0).all()
    head = seg == model.geom("actor000/head").id
    box_top = _rows(labels == 0)[0]
    assert box_top == _rows(umbrella)[0] and box_top < _rows(head)[0] - 5
    # The held hand is on the shaft: within hand + shaft radius of its axis.
    shaft = model.geom("actor000/umbrella_shaft").id
    axis = data.geom_xmat[shaft].reshape(3, 3)[:, 2]
    offset = data.geom_xpos[model.geom("actor000/hand_r").id] - data.geom_xpos[shaft]
    assert np.linalg.norm(offset - (offset @ axis) * axis) < 0.02
    # The canopy (1 m across, 0.2 m deep) is above the head and nearly level: its bounds are
    # wide and shallow (a 20 degree tilt would make them 0.2 cos 20 + 1 sin 20 = 0.53 m deep).
    canopy = model.geom("actor000/umbrella_canopy").id
    head_top = _world_aabb(model, data, [model.geom("actor000/head").id])[1][2]
    canopy_lo, canopy_hi = _world_aabb(model, data, [canopy])
    assert canopy_lo[2] > head_top + 0.05
    assert (canopy_hi - canopy_lo)[2] < 0.53 and ((canopy_hi - canopy_lo)[:2] > 0.9).all()

    plain, plain_data = _umbrella_scene(None)
    assert not [g for g in range(plain.ngeom) if "umbrella" in plain.geom(g).name]
    plain_seg = _segment(plain, plain_data)
    assert _rows(np.isin(plain_seg, _geoms(plain, "actor000/")))[0] > box_top + 5


@pytest.mark.parametrize("rider_height", [1.5, 1.75, 1.95])
@pytest.mark.parametrize("style", parts.BICYCLE_STYLES + parts.MOTORCYCLE_STYLES)
def test_every_vehicle_style_seats_its_rider_on_the_saddle(style, rider_height):
    """Pelvis on the saddle, hands on the grips, feet on the pedals / pegs / floorboard (3 cm),
    for short, average and tall riders; vehicle and rider inside the planning footprint."""
    bicycle = style in parts.BICYCLE_STYLES
    build = parts.PersonBuild(rider_height)
    spec = _spec((-6.0, 0.0, 1.5), 40.0)
    body = spec.worldbody.add_body(name="ride", pos=[0.0, 0.0, 0.0])
    if bicycle:  # the saddle set for the rider
        seat = parts.add_bicycle(body, "actor000/", (0.8, 0.1, 0.1), style, rider=build)
    else:
        seat = parts.add_motorcycle(body, "actor000/", (0.8, 0.1, 0.1), style)
    parts.add_rider(body, "actor001/", COLOURS, style, build=build, helmet=(0.9, 0.9, 0.9))
    model = spec.compile()
    data = mujoco.MjData(model)
    _pose(model, data, "actor001/", parts.riding_pose(style, build))
    mujoco.mj_forward(model, data)
    saddle = model.geom("actor000/" + ("saddle" if bicycle else "seat")).id
    saddle_lo, saddle_hi = _world_aabb(model, data, [saddle])
    assert seat == pytest.approx(saddle_hi[2], abs=1e-3)
    pelvis_lo, _ = _world_aabb(model, data, [model.geom("actor001/pelvis").id])
    assert 0.0 <= pelvis_lo[2] - saddle_hi[2] <= 0.03
    pelvis_x = data.geom_xpos[model.geom("actor001/pelvis").id][0]
    assert saddle_lo[0] < pelvis_x < saddle_hi[0]
    fit = parts.RIDER_FITS[style]
    for tag, foot in (("l", fit.foot_l), ("r", fit.foot_r)):
        hand = data.geom_xpos[model.geom(f"actor001/hand_{tag}").id][[0, 2]]
        assert np.linalg.norm(hand - fit.grip) < 0.03
        shin = model.body(f"actor001/shin_{tag}").id  # the ankle ends the shin
        ankle = data.xpos[shin] + data.xmat[shin].reshape(3, 3) @ [
            0, 0, -parts.body_proportions(build).shin]
        assert np.linalg.norm(ankle[[0, 2]] - foot) < 0.03
    # Vehicle and rider stay inside the footprint the layout plans with.
    length, width = L.FOOTPRINTS["bicycle" if bicycle else "motorcycle"]
    lo, hi = _world_aabb(model, data, _geoms(model, "actor0"))
    assert (np.abs([lo[0], hi[0]]) < length / 2).all()
    assert (np.abs([lo[1], hi[1]]) < width / 2).all()
    assert lo[2] > -1e-3


def _ankle(model, data, prefix, tag, build):
    shin = model.body(f"{prefix}shin_{tag}").id  # the ankle ends the shin
    return data.xpos[shin] + data.xmat[shin].reshape(3, 3) @ [0, 0, -parts.body_proportions(build).shin]


@pytest.mark.parametrize("rider_height", [1.5, 1.72, 1.95])
@pytest.mark.parametrize("style", parts.BICYCLE_STYLES)
def test_a_cyclist_s_feet_stay_on_the_pedals_all_the_way_round(style, rider_height):
    """Riders sat still with the cranks at 25 degrees; now the cranks turn and the legs follow.
    Over a whole turn each ankle stays where the foot on its pedal puts it (the pedal geom as
    MuJoCo poses it on the crank hinge), the knee never locks straight (the saddle is set for
    the rider's legs), and the left and right pedals stay opposite. The shortest riders (up to
    1.57 m on a city bicycle, 1.59 m on a road one: 5-8 %) have the saddle at its lowest; below
    1.52-1.54 m (1-2 %) they stretch at the bottom of the stroke, a foot up to 2.6 cm short of its
    pedal."""
    build = parts.PersonBuild(rider_height)
    lowest = parts.saddle_height(style, build) == parts.RIDER_FITS[style].saddle_top
    assert lowest == (rider_height == 1.5)
    spec = _spec((-6.0, 0.0, 1.5), 40.0)
    body = spec.worldbody.add_body(name="ride", pos=[0.0, 0.0, 0.0])
    parts.add_bicycle(body, "actor000/", (0.8, 0.1, 0.1), style, rider=build)
    parts.add_rider(body, "actor001/", COLOURS, style, build=build, helmet=(0.9, 0.9, 0.9))
    model = spec.compile()
    data = mujoco.MjData(model)
    crank = model.joint("actor000/crank").qposadr[0]
    pedal_ids = {tag: model.geom(f"actor000/pedal_{tag}").id for tag in "lr"}
    offset = np.array([parts._ANKLE_ABOVE_PEDAL[0], 0.0, parts._ANKLE_ABOVE_PEDAL[1]])
    heights, knees = [], []
    for distance in np.linspace(0.0, parts.PEDAL_DEVELOPMENT_M, 25):
        angle = parts.crank_angle(distance)
        data.qpos[crank] = angle
        pose = parts.riding_pose(style, build, angle)
        _pose(model, data, "actor001/", pose)
        mujoco.mj_forward(model, data)
        pedals = {tag: data.geom_xpos[pedal_ids[tag]] for tag in "lr"}
        np.testing.assert_allclose(pedals["l"][[0, 2]] + pedals["r"][[0, 2]],
                                   2 * np.array(parts.BOTTOM_BRACKET), atol=1e-9)
        for tag in "lr":
            ankle = _ankle(model, data, "actor001/", tag, build)
            assert np.linalg.norm((ankle - pedals[tag] - offset)[[0, 2]]) < (0.027 if lowest else 0.005)
            knees.append(pose[f"knee_{tag}"])
        heights.append(pedals["l"][2])
        for tag in "lr":  # round about the axle: the same to the eye at every angle
            axis = data.geom_xmat[pedal_ids[tag]].reshape(3, 3)[:, 2]
            assert model.geom_type[pedal_ids[tag]] == mujoco.mjtGeom.mjGEOM_CYLINDER
            assert abs(axis[1]) == pytest.approx(1.0)
        if distance == 0.0:  # riding forwards, the front (left) pedal starts down: the right way round
            front_z = pedals["l"][2]
        elif len(heights) == 2:
            assert pedals["l"][2] < front_z
    assert max(heights) - min(heights) == pytest.approx(2 * parts.CRANK_LENGTH, abs=0.01)
    assert parts.crank_angle(parts.PEDAL_DEVELOPMENT_M / 4) == pytest.approx(math.pi / 2)
    if not lowest:
        assert min(knees) > 0.3  # about 30 degrees at the bottom of the stroke, never straight


@pytest.mark.parametrize("style", parts.BICYCLE_STYLES)
def test_bicycle_wheels_are_see_through_rings(style):
    """A side view of the rear wheel: inside the rim, most pixels show what is behind."""
    # Camera 4 m to the right looking along +y at the rear axle: the axle is the image centre.
    rear_axle = -0.54 if style == "city" else -0.5
    spec = _spec((rear_axle, -4.0, 0.345 if style == "city" else 0.34), 30.0, _look_along_y())
    body = spec.worldbody.add_body(name="ride")
    parts.add_bicycle(body, "actor000/", (0.1, 0.1, 0.1), style)
    model = spec.compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    seg = _segment(model, data)
    focal = (H / 2) / math.tan(math.radians(15.0))
    rows, cols = np.mgrid[0:H, 0:W]
    radius_px = np.hypot(rows + 0.5 - H / 2, cols + 0.5 - W / 2)
    rim = focal * 0.30 / 4.0  # inside the rim (0.30 m), outside the hub (0.05 m)
    inside = (radius_px < 0.85 * rim) & (radius_px > focal * 0.06 / 4.0)
    bicycle = np.isin(seg, _geoms(model, "actor000/"))
    assert inside.sum() > 200
    assert bicycle[inside].mean() < 0.25
    ring = (radius_px > focal * 0.322 / 4.0) & (radius_px < focal * 0.338 / 4.0)
    assert bicycle[ring].mean() > 0.9  # the tyre itself is solid


def _look_along_y():
    """Camera quaternion: optical axis +y, image up +z (camera x = +x world)."""
    xaxis, yaxis = np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, np.column_stack([xaxis, yaxis, np.cross(xaxis, yaxis)]).ravel())
    return quat


def test_vehicle_style_errors_name_the_styles():
    spec = mujoco.MjSpec()
    with pytest.raises(ValueError, match=r"bicycle style: expected one of city, road, got 'bmx'"):
        parts.add_bicycle(spec.worldbody, "a/", (1, 0, 0), "bmx")
    with pytest.raises(ValueError, match=r"motorcycle style: expected one of standard, sport, "
                                         r"scooter, got 'city'"):
        parts.add_motorcycle(spec.worldbody, "a/", (1, 0, 0), "city")
    with pytest.raises(ValueError, match=r"vehicle style: expected one of city, .*got 'tram'"):
        parts.riding_pose("tram")


def test_walking_pose_is_periodic_alternating_and_defaults_to_the_old_gait():
    gait = parts.sample_gait(np.random.default_rng(4), parts.PersonBuild())
    for phase in np.linspace(0, 2 * math.pi, 13):
        now, later = parts.walking_pose(phase, gait), parts.walking_pose(phase + 2 * math.pi, gait)
        assert now == pytest.approx(later, abs=1e-12)
        half = parts.walking_pose(phase + math.pi, gait)
        for left, right in (("hip_l", "hip_r"), ("knee_l", "knee_r"),
                            ("shoulder_l", "shoulder_r"), ("elbow_l", "elbow_r")):
            assert now[left] == pytest.approx(half[right], abs=1e-12)
        assert now["hip_l"] == pytest.approx(-now["hip_r"])
        assert now["hip_l"] * now["shoulder_l"] <= 0  # arms swing against the legs
    old = parts.walking_pose(0.7)  # the formula every person walked with before gaits
    swing = math.sin(0.7)
    assert old["hip_l"] == pytest.approx(-0.45 * swing)
    assert old["knee_l"] == pytest.approx(0.15 + 0.55 * math.sin(0.7 + math.pi / 2) ** 2)
    assert old["shoulder_r"] == pytest.approx(-0.4 * swing) and old["elbow_l"] == -0.35
    assert list(old) == list(parts.PERSON_JOINTS)


def test_standing_pose_sways_within_small_angles():
    angles = np.array([[parts.standing_pose(t, 1.3)[j] for j in parts.PERSON_JOINTS]
                       for t in np.linspace(0, 20, 201)])
    assert np.abs(angles).max() <= 0.2
    assert np.ptp(angles, axis=0).max() > 0.05  # it does move
    other = parts.standing_pose(3.0, 2.5)
    assert other != parts.standing_pose(3.0, 1.3)


def test_samplers_are_deterministic_by_rng_and_follow_their_ranges():
    def builds(seed, n=300, p=0.15):
        rng = np.random.default_rng(seed)
        return [parts.sample_person_build(rng, p) for _ in range(n)]
    assert builds(1) == builds(1) and builds(1) != builds(2)
    sample = builds(3, 600)
    children = [b for b in sample if b.is_child]
    assert 0.10 < len(children) / len(sample) < 0.20
    assert all(1.0 <= b.height_m <= 1.4 for b in children)
    assert all(1.5 <= b.height_m <= 1.95 for b in sample if not b.is_child)
    assert {b.clothing for b in sample} == set(parts.CLOTHING_STYLES)
    assert {b.hat for b in sample} == set(parts.HAT_STYLES)
    assert all(0.85 <= b.girth <= 1.3 for b in sample)
    assert not any(b.is_child for b in builds(4, 50, 0.0))
    child, adult = parts.PersonBuild(1.2), parts.PersonBuild(1.8)
    gait = parts.sample_gait(np.random.default_rng(7), child)
    assert gait == parts.sample_gait(np.random.default_rng(7), child)
    assert gait != parts.sample_gait(np.random.default_rng(8), child)
    assert parts.gait_cycle_length(child, gait) < parts.gait_cycle_length(adult, gait)
    assert 1.2 < parts.gait_cycle_length() < 1.7 and 1.2 < parts.gait_speed() < 1.6
    with pytest.raises(ValueError, match=r"child_probability: expected 0..1, got 1.5"):
        parts.sample_person_build(np.random.default_rng(0), 1.5)


def test_person_build_rejects_bad_values():
    with pytest.raises(ValueError, match=r"height_m: expected 0.9..2.1 metres, got 3.0"):
        parts.PersonBuild(height_m=3.0)
    with pytest.raises(ValueError, match=r"clothing: expected one of trousers, shorts, skirt, "
                                         r"long_coat, got 'kilt'"):
        parts.PersonBuild(clothing="kilt")
    with pytest.raises(ValueError, match=r"colours: expected keys shirt, trousers and skin, "
                                         r"missing skin"):
        parts.add_person(mujoco.MjSpec().worldbody, "a/", {"shirt": (1, 0, 0),
                                                           "trousers": (0, 0, 1)})


def test_old_signatures_still_build_the_old_adult_and_vehicles():
    spec = _spec((0.0, 0.0, 1.5), 40.0)
    walker = spec.worldbody.add_body(name="walker", pos=[6.0, 0.0, 0.0])
    parts.add_person(walker, "actor000/", COLOURS)
    bike = spec.worldbody.add_body(name="bike", pos=[6.0, 3.0, 0.0])
    saddle = parts.add_bicycle(bike, "actor001/", (0.2, 0.2, 0.8))
    moto = spec.worldbody.add_body(name="moto", pos=[6.0, -3.0, 0.0])
    seat = parts.add_motorcycle(moto, "actor002/", (0.2, 0.8, 0.2))
    assert saddle == parts.saddle_height("city") and seat == parts.RIDER_FITS[
        "standard"].saddle_top
    model = spec.compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    for joint in parts.PERSON_JOINTS:
        assert model.joint("actor000/" + joint).type == mujoco.mjtJoint.mjJNT_HINGE
    assert data.xpos[model.body("actor000/thigh_l").id][2] == pytest.approx(0.93, abs=0.002)
    person = _geoms(model, "actor000/")
    lo, hi = _world_aabb(model, data, person)
    assert hi[2] == pytest.approx(1.76, abs=0.015) and lo[2] == pytest.approx(0.0, abs=0.005)
    assert 15 <= len(person) <= 30
    actors = [g for g in range(model.ngeom) if model.geom(g).name.startswith("actor")]
    assert len(actors) == model.ngeom - 1  # every part is named after its actor
    assert (model.geom_contype[actors] == 0).all() and (model.geom_conaffinity[actors] == 0).all()
    # Meshes survive the MJCF round trip of `rainbench scene`.
    again = mujoco.MjModel.from_xml_string(spec.to_xml())
    assert again.ngeom == model.ngeom and again.nmesh == model.nmesh > 0


def test_every_build_option_compiles_within_the_geom_budget():
    spec = _spec((0.0, 0.0, 1.5), 40.0)
    options = [parts.PersonBuild(1.6, 1.3, clothing, clothing == "long_coat", hair, hat)
               for clothing, hair, hat in zip(parts.CLOTHING_STYLES, parts.HAIR_STYLES,
                                              parts.HAT_STYLES)]
    for index, build in enumerate(options):
        body = spec.worldbody.add_body(name=f"u{index}", pos=[5.0, index - 2.0, 0.0])
        parts.add_person(body, f"actor{index:03d}/", COLOURS, build=build,
                         umbrella=(0.2, 0.2, 0.2))
    model = spec.compile()
    for index in range(len(options)):
        assert 15 <= len(_geoms(model, f"actor{index:03d}/")) <= 30


def _volume_and_open_edges(vertices, faces):
    v0, v1, v2 = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    volume = np.einsum("ij,ij->i", v0, np.cross(v1, v2)).sum() / 6
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), 1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return volume, int((counts != 2).sum())


def test_part_meshes_are_closed_and_outward_with_known_volumes():
    torus = parts.tube_ring_mesh(1.0, 0.1, 0.1, segments=96, sides=48)
    volume, open_edges = _volume_and_open_edges(*torus)
    assert open_edges == 0 and volume == pytest.approx(2 * math.pi ** 2 * 0.1 ** 2, rel=0.01)
    half = parts.tube_ring_mesh(1.0, 0.1, 0.1, arc=(0.0, math.pi), segments=48, sides=48)
    volume, open_edges = _volume_and_open_edges(*half)
    assert open_edges == 0 and volume == pytest.approx(math.pi ** 2 * 0.1 ** 2, rel=0.01)
    box = parts.loft_mesh([(0.0, 0.5, 0.25, 0.0, 60.0), (2.0, 0.5, 0.25, 0.0, 60.0)], around=64)
    volume, open_edges = _volume_and_open_edges(*box)  # a near-box 1 x 0.5 x 2
    assert open_edges == 0 and volume == pytest.approx(1.0, rel=0.03)
    body = parts.side_loft_mesh([(2.0, 0.0, 0.5, 0.5, 60.0), (0.0, 0.0, 0.5, 0.5, 60.0)],
                                around=64)
    volume, open_edges = _volume_and_open_edges(*body)  # a near-box 2 x 1 x 0.5
    assert open_edges == 0 and volume == pytest.approx(1.0, rel=0.03)
    canopy = parts.canopy_mesh(0.5, 0.2, thickness=0.01)
    volume, open_edges = _volume_and_open_edges(*canopy)
    assert open_edges == 0 and 0.0 < volume < math.pi * 0.5 ** 2 * 0.01 * 1.2
    assert canopy[0][:, 2].max() == pytest.approx(0.2)
