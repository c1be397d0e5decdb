"""rainbench stats: every number on tiny shards with known boxes, computed here by hand."""

import json

import pytest
from labelled_shards import OLD_CLASS_NAMES, write_labelled_shard

from rainbench import cli
from rainbench.store.shard import ShardFormatError
from rainbench.store.stats import dataset_stats, render_stats

PERSON, CAR, BUS, TRUCK = 0, 2, 5, 7


def box(height, x=5):
    return (x, 0, x + 10, height)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """Three shards, two scenes (seeds 3 and 4); scene 3 is split over two shards.

    A = scene 3 frames 0-1 (an old 4-name shard, layout intersection, night),
    C = scene 3 frame 2 (intersection, night), B = scene 4 frames 0-2 (no layout / time of day).
    """
    root = tmp_path_factory.mktemp("stats")
    night = {"layout": "intersection", "time_of_day": "night"}
    write_labelled_shard(root, [
        [(PERSON, 1, box(10), 0.95, 0.0), (CAR, 2, box(20), 0.55, 0.25), (CAR, 3, box(30), 0.15, 0.0)],
        [(PERSON, 1, box(12), 1.0, 0.05), (CAR, 2, box(22), 0.65, 0.35)],
    ], scene_seed=3, class_names=OLD_CLASS_NAMES, attrs=night, rates=(0.0, 50.0))
    write_labelled_shard(root, [[(CAR, 2, box(24), 0.75, 0.45)]], scene_seed=3, frame_offset=2, attrs=night,
                         rates=(0.0, 50.0))
    write_labelled_shard(root, [
        [(BUS, 1, box(40), 0.45, 0.0)],
        [],
        [(BUS, 1, box(44), 0.45, 0.0), (PERSON, 2, box(14), 0.85, 0.0), (TRUCK, 5, box(50), 1.0, 0.5)],
    ], scene_seed=4, rates=(0.0, 50.0),
        ignore=[[], [(PERSON, 7, (5, 5, 8, 12))], [(CAR, 8, (60, 5, 63, 9)), (PERSON, 7, (6, 5, 9, 12))]])
    return root


def by_class(stats):
    return {entry["class"]: entry for entry in stats["classes"]}


def test_objects_instances_and_frames(data):
    stats = dataset_stats(data)
    assert (stats["shards"], stats["scenes"], stats["frames"]) == (3, 2, 6)
    # scene 3: person 1, cars 2 and 3 (car 2 spans both of its shards); scene 4: bus 1, person 2,
    # truck 5. Instance ids repeat across scenes (person 1 vs bus 1) and still count apart.
    assert (stats["objects"], stats["instances"]) == (6, 10)  # labels once per frame, not per rate
    assert [(c["class_id"], c["class"], c["objects"], c["instances"]) for c in stats["classes"]] == [
        (0, "person", 2, 3), (2, "car", 2, 4), (5, "bus", 1, 2), (7, "truck", 1, 1)]  # only classes present
    # visible actors too small to be labels, counted per frame like instances (only B has any)
    assert stats["ignore_regions"] == 3
    assert [c["ignore_regions"] for c in stats["classes"]] == [2, 1, 0, 0]


def test_shards_of_different_rate_lists_count_together(data, tmp_path):
    """Labels are the same at every rate: a folder of shards written with other rate lists was
    refused with advice (select rates) that `stats` has no flag for."""
    import shutil

    for shard in sorted(data.glob("*.h5")):
        shutil.copy(shard, tmp_path / shard.name)
    write_labelled_shard(tmp_path, [[(CAR, 1, box(30), 1.0, 0.0)]], scene_seed=9, rates=(25.0,))
    stats = dataset_stats(tmp_path)
    assert (stats["shards"], stats["scenes"], stats["frames"], stats["objects"]) == (4, 3, 7, 7)


def test_height_percentiles(data):
    heights = {name: entry["height_px"] for name, entry in by_class(dataset_stats(data)).items()}
    # linear interpolation: position p/100 * (n - 1) in the sorted heights
    expected = {
        "person": [10.2, 11.0, 12.0, 13.0, 13.8],  # 10, 12, 14
        "car": [20.3, 21.5, 23.0, 25.5, 29.1],  # 20, 22, 24, 30
        "bus": [40.2, 41.0, 42.0, 43.0, 43.8],  # 40, 44
        "truck": [50.0] * 5,
    }
    for name, values in expected.items():
        assert [heights[name][f"p{p}"] for p in (5, 25, 50, 75, 95)] == pytest.approx(values, rel=1e-12)


def test_visibility_and_truncation_histograms(data):
    stats = dataset_stats(data)
    assert stats["bins"] == [0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0]
    classes = by_class(stats)
    assert classes["person"]["visible_fraction_hist"] == [0, 0, 0, 0, 0, 0, 0, 0, 1, 2]  # 1.0 in the last
    assert classes["car"]["visible_fraction_hist"] == [0, 1, 0, 0, 0, 1, 1, 1, 0, 0]
    assert classes["bus"]["visible_fraction_hist"] == [0, 0, 0, 0, 2, 0, 0, 0, 0, 0]
    assert classes["truck"]["visible_fraction_hist"] == [0, 0, 0, 0, 0, 0, 0, 0, 0, 1]
    assert classes["person"]["truncation_hist"] == [3, 0, 0, 0, 0, 0, 0, 0, 0, 0]
    assert classes["car"]["truncation_hist"] == [1, 0, 1, 1, 1, 0, 0, 0, 0, 0]
    assert classes["bus"]["truncation_hist"] == [2, 0, 0, 0, 0, 0, 0, 0, 0, 0]
    assert classes["truck"]["truncation_hist"] == [0, 0, 0, 0, 0, 1, 0, 0, 0, 0]


def test_instances_per_frame(data):
    stats = dataset_stats(data)
    classes = by_class(stats)
    # frames: A0 A1 C0 B0 B1 B2; person 1 1 0 0 0 1, car 2 1 1 0 0 0, bus 0 0 0 1 0 1, truck ... 1
    assert classes["person"]["per_frame"] == {"mean": pytest.approx(3 / 6), "max": 1, "hist": [3, 3]}
    assert classes["car"]["per_frame"] == {"mean": pytest.approx(4 / 6), "max": 2, "hist": [3, 2, 1]}
    assert classes["bus"]["per_frame"] == {"mean": pytest.approx(2 / 6), "max": 1, "hist": [4, 2]}
    assert classes["truck"]["per_frame"] == {"mean": pytest.approx(1 / 6), "max": 1, "hist": [5, 1]}
    # all classes: 3 2 1 1 0 3
    assert stats["per_frame"] == {"mean": pytest.approx(10 / 6), "max": 3, "hist": [1, 2, 1, 2]}


def test_layout_and_time_of_day_counts_with_the_fallback(data):
    stats = dataset_stats(data)
    scene3 = {"scenes": 1, "frames": 3, "objects": 3, "instances": 6}
    scene4 = {"scenes": 1, "frames": 3, "objects": 3, "instances": 4}
    assert stats["layout"] == {"intersection": scene3, "street": scene4}  # B has no layout attr
    assert stats["time_of_day"] == {"day": scene4, "night": scene3}  # nor a time of day


def _run(capsys, *argv):
    code = cli.main([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _row(text, title, first):
    """The cells of the row starting with ``first`` in the table under the line ``title``."""
    block = text.split(title, 1)[1].split("\n\n", 1)[0]
    return next(line.split() for line in block.splitlines() if line.split() and line.split()[0] == first)


def test_cli_tables_and_json_agree(data, capsys):
    code, text, err = _run(capsys, "stats", data)
    assert code == 0 and err == ""
    code, out, err = _run(capsys, "stats", data, "--json")
    assert code == 0 and err == ""
    parsed = json.loads(out)
    assert parsed == json.loads(json.dumps(dataset_stats(data)))
    assert render_stats(parsed) == text  # the table is a rendering of exactly the JSON
    assert text.splitlines()[1].startswith("3 shards, 2 scenes, 6 frames; 6 objects, 10 instances")
    assert "; 3 ignore regions (visible actors too small or hidden to be labels)" in text.splitlines()[1]
    table_one = "Objects and instances per class"
    assert _row(text, table_one, "car") == ["car", "2", "2", "4", "1"]
    assert _row(text, table_one, "truck") == ["truck", "7", "1", "1", "0"]
    assert _row(text, table_one, "all") == ["all", "6", "10", "3"]
    assert "bicycle" not in text and "motorcycle" not in text
    assert _row(text, "Box height (px) percentiles", "car") == ["car", "20.3", "21.5", "23.0", "25.5", "29.1"]
    assert _row(text, "Visible fraction", "car") == ["car", "0", "1", "0", "0", "0", "1", "1", "1", "0", "0"]
    assert _row(text, "Truncation", "truck") == ["truck", "0", "0", "0", "0", "0", "1", "0", "0", "0", "0"]
    assert _row(text, "Instances per frame", "car") == ["car", "0.67", "2", "3", "2", "1"]
    assert _row(text, "Instances per frame", "all") == ["all", "1.67", "3", "1", "2", "1", "2"]
    assert _row(text, "Per layout", "street") == ["street", "1", "3", "3", "4"]
    assert _row(text, "Per time of day", "night") == ["night", "1", "3", "3", "6"]
    lines = text.splitlines()
    header = lines.index("Objects and instances per class (the seed paper's Table I)") + 1
    assert len({len(line) for line in lines[header:header + 2]}) == 1  # header and rule aligned


def test_one_shard_reads_alone(data):
    stats = dataset_stats(data / "scene000004_f00000.h5")
    assert (stats["shards"], stats["frames"], stats["objects"], stats["instances"]) == (1, 3, 3, 4)


def test_bad_paths_and_corrupt_shards_are_one_line_errors(data, tmp_path, capsys):
    missing = tmp_path / "nope"
    code, out, err = _run(capsys, "stats", missing)
    assert code == 2 and out == "" and err.strip() == f"rainbench: error: {missing}: no such dataset directory or shard"
    empty = tmp_path / "empty"
    empty.mkdir()
    code, _, err = _run(capsys, "stats", empty, "--json")
    assert code == 2 and err.strip() == f"rainbench: error: {empty}: no shards (scene*_f*.h5) found"
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "scene000000_f00000.h5").write_bytes((data / "scene000004_f00000.h5").read_bytes()[:3000])
    code, _, err = _run(capsys, "stats", broken)
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert err.startswith(f"rainbench: error: {broken / 'scene000000_f00000.h5'}: ")
    with pytest.raises(ShardFormatError, match="scene000000_f00000.h5: not a readable HDF5 shard"):
        dataset_stats(broken)


def test_classes_seen_only_as_ignore_regions_are_counted(tmp_path, capsys):
    """The per-class ignore column did not add up to "all": a class with ignore regions and no
    label (at small sizes most people and bikes) was left out."""
    root = tmp_path / "only"
    root.mkdir()
    write_labelled_shard(root, [[(CAR, 1, box(24), 1.0, 0.0)], []],
                         ignore=[[(PERSON, 7, (5, 5, 8, 12))], [(PERSON, 7, (6, 5, 9, 12)), (3, 9, (30, 5, 33, 9))]])
    stats = dataset_stats(root)
    assert [c["class"] for c in stats["classes"]] == ["car"]
    assert stats["ignore_only_classes"] == [{"class_id": 0, "class": "person", "ignore_regions": 2},
                                            {"class_id": 3, "class": "motorcycle", "ignore_regions": 1}]
    assert sum(c["ignore_regions"] for c in stats["classes"] + stats["ignore_only_classes"]) == stats["ignore_regions"]
    text = render_stats(stats)
    table = text.split("(the seed paper's Table I)", 1)[1].split("\n\n", 1)[0]
    rows = [line.split() for line in table.splitlines()[3:]]
    assert rows == [["person", "0", "0", "0", "2"], ["car", "2", "1", "1", "0"],
                    ["motorcycle", "3", "0", "0", "1"], ["all", "1", "1", "3"]]
