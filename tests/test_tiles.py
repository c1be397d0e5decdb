"""Training tiles (rainbench.experiments.tiles): labels cut exactly, placements inside the image and on
the picked objects, the covering grid, seeded exports, rain on training tiles (rain sources drawn
by weight, RandomRain) that moves no tile, and one-line errors for bad settings."""

import dataclasses

import cv2
import numpy as np
import pytest

from rainbench.experiments import tiles
from rainbench.store.export import read_yolo_labels


def test_cut_boxes_clips_and_drops_by_area_fraction():
    boxes = np.array([[10, 10, 30, 50],      # inside the tile at (0, 0), size 64
                      [50, 0, 90, 20],       # 14 of 40 px wide inside: 35 % of its area
                      [60, 60, 100, 100],    # 4x4 of 40x40 inside: 1 %
                      [200, 200, 210, 210]],  # outside
                     dtype=np.float32)
    classes = np.array([0, 1, 2, 3])
    kept, kept_classes = tiles.cut_boxes(boxes, classes, (0, 0), 64, min_area_fraction=0.25)
    np.testing.assert_allclose(kept, [[10, 10, 30, 50], [50, 0, 64, 20]])
    assert kept_classes.tolist() == [0, 1] and kept.dtype == np.float32
    # Shifted origin: coordinates become tile pixels.
    kept, kept_classes = tiles.cut_boxes(boxes, classes, (40, 0), 64, min_area_fraction=0.25)
    np.testing.assert_allclose(kept, [[10, 0, 50, 20]])  # the third keeps 10 % only
    assert kept_classes.tolist() == [1]
    # A stricter share drops the cut box.
    kept, _ = tiles.cut_boxes(boxes, classes, (0, 0), 64, min_area_fraction=0.5)
    np.testing.assert_allclose(kept, [[10, 10, 30, 50]])
    with pytest.raises(tiles.TileError, match="expected one class id per box: got 4 boxes and 3"):
        tiles.cut_boxes(boxes, classes[:3], (0, 0), 64, 0.25)


def test_sampled_tiles_hold_the_picked_object_and_stay_inside():
    config = tiles.TileConfig(size=64, per_image=64, background=0.0, seed=0)
    boxes = np.array([[150, 20, 170, 60], [5, 100, 25, 120]], dtype=np.float32)
    classes = np.array([0, 3])
    rng = np.random.default_rng(1)
    # Only class 3 has weight: every tile must hold the whole second box.
    origins = tiles.sample_tile_origins(boxes, classes, (128, 192), config, np.array([0, 0, 0, 1.0]), rng)
    assert origins.shape == (64, 2)
    x0, y0 = origins.T
    assert (x0 >= 0).all() and (x0 <= 192 - 64).all() and (y0 >= 0).all() and (y0 <= 128 - 64).all()
    assert (x0 <= 5).all() and (x0 + 64 >= 25).all() and (y0 <= 100).all() and (y0 + 64 >= 120).all()
    assert len(set(map(tuple, origins))) > 20  # placements vary
    # Background tiles fall anywhere; with no box every tile is a background tile.
    anywhere = tiles.sample_tile_origins(np.zeros((0, 4)), np.zeros(0, int), (128, 192), config,
                                         np.ones(4), np.random.default_rng(2))
    assert anywhere[:, 0].max() > 100 and anywhere[:, 0].min() < 20
    # A box larger than the tile keeps its centre inside.
    big = tiles.sample_tile_origins(np.array([[0, 0, 192, 128]]), np.array([2]), (128, 192), config,
                                    np.ones(4), np.random.default_rng(3))
    assert ((big[:, 0] <= 96) & (big[:, 0] + 64 >= 96) & (big[:, 1] <= 64)).all()
    with pytest.raises(tiles.TileError, match=r"tiles.size: 64 px is larger than the rescaled image \(50x40\)"):
        tiles.sample_tile_origins(boxes, classes, (40, 50), config, np.ones(4), rng)


def test_grid_covers_every_pixel_with_the_fewest_tiles():
    origins = tiles.grid_tile_origins((480, 640), 320)
    assert origins.tolist() == [[0, 0], [320, 0], [0, 160], [320, 160]]
    covered = np.zeros((480, 640), bool)
    for x0, y0 in origins:
        covered[y0:y0 + 320, x0:x0 + 320] = True
    assert covered.all()
    assert tiles.grid_tile_origins((320, 320), 320).tolist() == [[0, 0]]


def test_tile_config_errors_are_one_line():
    with pytest.raises(tiles.TileError, match=r"tiles.size: expected a multiple of 32 in 32..4096 px, got 300"):
        tiles.TileConfig(size=300)
    with pytest.raises(tiles.TileError, match=r"tiles.background: expected a share in 0..1, got 2"):
        tiles.TileConfig(background=2)
    with pytest.raises(tiles.TileError, match=r"tiles.sise is not a tile setting"):
        tiles.TileConfig.from_mapping({"sise": 320})


def _yolo_folder(root, count, size=(160, 240)):
    (root / "images").mkdir(parents=True)
    (root / "labels").mkdir()
    rng = np.random.default_rng(0)
    height, width = size
    for index in range(count):
        image = rng.integers(0, 255, (height, width, 3), dtype=np.uint8)
        cv2.imwrite(str(root / "images" / f"{index:06d}.png"), image)
        # one person box 20x40 px at a known place, one car box
        (root / "labels" / f"{index:06d}.txt").write_text(
            f"0 {50 / width:.6f} {60 / height:.6f} {20 / width:.6f} {40 / height:.6f}\n"
            f"2 {120 / width:.6f} {30 / height:.6f} {30 / width:.6f} {20 / height:.6f}\n")
    return root


def test_export_tiles_rescales_crops_and_is_seeded(tmp_path):
    source = _yolo_folder(tmp_path / "src", 3)
    config = tiles.TileConfig(size=64, scale=0.5, per_image=3, background=0.0, seed=5)
    assert tiles.export_tiles(source, tmp_path / "a", config, grid=False, num_classes=4) == 9
    assert tiles.export_tiles(source, tmp_path / "b", config, grid=False, num_classes=4) == 9
    names = sorted(p.name for p in (tmp_path / "a" / "images").iterdir())
    assert names[:3] == ["000000_t00.png", "000000_t01.png", "000000_t02.png"] and len(names) == 9
    for name in names:
        first = (tmp_path / "a" / "images" / name).read_bytes()
        assert first == (tmp_path / "b" / "images" / name).read_bytes()
        image = cv2.imread(str(tmp_path / "a" / "images" / name))
        assert image.shape == (64, 64, 3)
        boxes, classes = read_yolo_labels(tmp_path / "a" / "labels" / name.replace(".png", ".txt"), 64, 64)
        # At scale 0.5 the person is 10x20 px and the car 15x10 px: whole ones keep that size.
        for box, class_id in zip(boxes, classes):
            size = box[2:] - box[:2]
            if class_id == 0 and (box[0] > 0.5 and box[2] < 63.5 and box[1] > 0.5 and box[3] < 63.5):
                np.testing.assert_allclose(size, [10, 20], atol=1e-3)
        assert len(classes) >= 1  # every tile sits on an object (background=0)
    # The tile's pixels are the rescaled image's pixels at its origin.
    scaled = cv2.resize(cv2.imread(str(source / "images" / "000000.png")), (120, 80),
                        interpolation=cv2.INTER_LINEAR)
    with pytest.raises(tiles.TileError, match="larger than the rescaled image"):
        tiles.export_tiles(source, tmp_path / "c", tiles.TileConfig(size=64, scale=0.375), grid=True,
                           num_classes=4)
    grid = tiles.export_tiles(source, tmp_path / "g", tiles.TileConfig(size=32, scale=0.5), grid=True,
                              num_classes=4)
    assert grid == 3 * 12  # 120x80 covered by 4x3 tiles of 32
    first_tile = cv2.imread(str(tmp_path / "g" / "images" / "000000_t00.png"))
    np.testing.assert_array_equal(first_tile, scaled[:32, :32])
    # Another seed places tiles elsewhere.
    tiles.export_tiles(source, tmp_path / "d", tiles.TileConfig(size=64, scale=0.5, per_image=3, background=0.0, seed=6),
                       grid=False, num_classes=4)
    assert any((tmp_path / "d" / "labels" / n.replace(".png", ".txt")).read_text() !=
               (tmp_path / "a" / "labels" / n.replace(".png", ".txt")).read_text() for n in names)
    with pytest.raises(tiles.TileError, match="no .png images"):
        tiles.export_tiles(tmp_path / "empty", tmp_path / "e", config, grid=True, num_classes=4)


def _marked_copy(source, root, base):
    """``source``'s frames as another YOLO folder whose image ``i`` is the constant ``base + i``
    (so a tile tells its folder and frame apart), with the same labels."""
    (root / "images").mkdir(parents=True)
    (root / "labels").mkdir()
    for index, path in enumerate(sorted((source / "images").glob("*.png"))):
        shape = cv2.imread(str(path)).shape
        cv2.imwrite(str(root / "images" / path.name), np.full(shape, base + index, np.uint8))
        label = path.with_suffix(".txt").name
        (root / "labels" / label).write_text((source / "labels" / label).read_text())
    return root


def _tile_files(folder):
    return {path.relative_to(folder): path.read_bytes() for path in sorted(folder.rglob("*")) if path.is_file()}


def test_rain_sources_are_drawn_per_tile_in_their_weights_by_seed(tmp_path):
    """Each training tile is cut from one rain source, drawn with the weights (2:1:1) from the
    tile seed's own generator: the tiles' places and labels are the clean cut's."""
    clean = _yolo_folder(tmp_path / "src", 30)
    bases = (10, 90, 170)  # frame i of source k is the constant bases[k] + i (i < 30)
    folders = [_marked_copy(clean, tmp_path / f"rate{k}", base) for k, base in enumerate(bases)]
    config = tiles.TileConfig(size=32, scale=0.5, per_image=8, background=0.3, seed=3)
    rain_sources = list(zip(folders, (2.0, 1.0, 1.0)))
    assert tiles.export_tiles(folders[0], tmp_path / "a", config, grid=False, num_classes=4,
                              rain_sources=rain_sources) == 240
    tiles.export_tiles(folders[0], tmp_path / "clean", config, grid=False, num_classes=4)
    drawn = []
    for path in sorted((tmp_path / "a" / "images").iterdir()):
        image, frame = cv2.imread(str(path)), int(path.stem.split("_")[0])
        assert (image == image[0, 0, 0]).all()
        drawn.append(bases.index(int(image[0, 0, 0]) - frame))  # the frame's own pixels, of one source
    counts = np.bincount(drawn, minlength=3)
    for count, share in zip(counts, (0.5, 0.25, 0.25)):
        assert abs(count - 240 * share) < 4 * (240 * share * (1 - share)) ** 0.5, counts
    files = _tile_files(tmp_path / "a")
    labels = {name: data for name, data in files.items() if name.parts[0] == "labels"}
    assert labels == {name: data for name, data in _tile_files(tmp_path / "clean").items()
                      if name.parts[0] == "labels"}  # rain moves no tile
    tiles.export_tiles(folders[0], tmp_path / "b", config, grid=False, num_classes=4, rain_sources=rain_sources)
    assert _tile_files(tmp_path / "b") == files  # the same seed, the same files
    tiles.export_tiles(folders[0], tmp_path / "c", dataclasses.replace(config, seed=4), grid=False,
                       num_classes=4, rain_sources=rain_sources)
    assert [cv2.imread(str(p))[0, 0, 0] - int(p.stem[:6]) for p in sorted((tmp_path / "c" / "images").iterdir())] \
        != [bases[k] for k in drawn]
    with pytest.raises(tiles.TileError, match="rain is for training tiles only"):
        tiles.export_tiles(folders[0], tmp_path / "g", config, grid=True, num_classes=4, rain_sources=rain_sources)
    (folders[2] / "labels" / "000003.txt").write_text("")
    with pytest.raises(tiles.TileError, match=r"rate2/labels/000003.txt: labels differ from .*rate0/labels/000003.txt"):
        tiles.export_tiles(folders[0], tmp_path / "d", config, grid=False, num_classes=4, rain_sources=rain_sources)
    (folders[2] / "images" / "000003.png").unlink()
    with pytest.raises(tiles.TileError, match=r"rate2/images: holds other images than .*rate0/images"):
        tiles.export_tiles(folders[0], tmp_path / "d", config, grid=False, num_classes=4, rain_sources=rain_sources)


def test_random_rain_rains_on_about_p_of_the_training_tiles_by_seed(tmp_path):
    from rainbench.experiments.shard_training import RandomRainAugment

    source = _yolo_folder(tmp_path / "src", 20)
    config = tiles.TileConfig(size=32, scale=0.5, per_image=6, background=0.3, seed=1)
    rain = RandomRainAugment(p=0.3)
    tiles.export_tiles(source, tmp_path / "clean", config, grid=False, num_classes=4)
    tiles.export_tiles(source, tmp_path / "rain", config, grid=False, num_classes=4, random_rain=rain)
    clean, rained = _tile_files(tmp_path / "clean"), _tile_files(tmp_path / "rain")
    assert clean.keys() == rained.keys()
    assert all(rained[name] == data for name, data in clean.items() if name.parts[0] == "labels")
    changed = sum(rained[name] != data for name, data in clean.items() if name.parts[0] == "images")
    assert abs(changed - 120 * 0.3) < 4 * (120 * 0.3 * 0.7) ** 0.5, changed
    tiles.export_tiles(source, tmp_path / "again", config, grid=False, num_classes=4, random_rain=rain)
    assert _tile_files(tmp_path / "again") == rained
    with pytest.raises(tiles.TileError, match="rain is for training tiles only"):
        tiles.export_tiles(source, tmp_path / "g", config, grid=True, num_classes=4, random_rain=rain)


def test_a_tile_sets_name_tells_its_rain():
    config = tiles.TileConfig()
    assert config.token() == config.token(None) == "tiles_s320_x1_n2_b0.2_a0.1_r0"
    rain = {"rain_curriculum": [{"rain_model": "physical", "rate": 50.0, "weight": 1.0}], "random_rain": None}
    other = {"rain_curriculum": [{"rain_model": "physical", "rate": 50.0, "weight": 2.0}], "random_rain": None}
    assert config.token(rain).startswith("tiles_s320_x1_n2_b0.2_a0.1_r0_rain")
    assert config.token(rain) == config.token(dict(rain)) != config.token(other)
