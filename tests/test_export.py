"""YOLO / COCO exports and preview videos round-trip against the shards they came from."""

import json

import cv2
import numpy as np
import pytest

from rainbench.store import video as video_module
from rainbench.gen.config import DatasetConfig
from rainbench.gen.dataset import run_dataset
from rainbench.store import Dataset, list_shards
from rainbench.store.export import (ExportError, export_coco, export_yolo,
                                  read_yolo_labels)
from rainbench.store.shard import open_shard, read_frame_ignore, read_frame_labels
from rainbench.store.video import write_videos

RATES = (0.0, 50.0)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """Two shards (frames 0-1 and 2) of one scene at 0 and 50 mm/h, 96 x 72."""
    root = tmp_path_factory.mktemp("data")
    # the residential street: its parked cars are near enough to label at 96x72
    run_dataset(DatasetConfig(scenes=1, frames=3, frames_per_shard=2, width=96, height=72,
                              rates=RATES, layout="residential", time_of_day="day"), root)
    return root


def shard_truth(root):
    """[(image_id, shard, frame, rgb (R, H, W, 3), labels)] in image-id order."""
    truth = []
    for image in Dataset(root).images:
        image_id, path, frame = image.image_id, image.shard, image.frame
        with open_shard(path) as handle:
            truth.append((image_id, path, frame, handle["rgb"][:, frame],
                          read_frame_labels(handle, frame)))
    return truth


def test_yolo_round_trip(dataset, tmp_path):
    truth = shard_truth(dataset)
    assert len(list_shards(dataset)) == 2 and [t[0] for t in truth] == [1, 2, 3]
    assert sum(len(t[4]["bbox"]) for t in truth) > 0
    out = tmp_path / "yolo"
    yamls = export_yolo(dataset, out)
    assert yamls == [out / "rate_0" / "data.yaml", out / "rate_50" / "data.yaml"]
    assert sorted(p.name for p in out.iterdir()) == ["rate_0", "rate_50"]
    for rate_index, data_yaml in enumerate(yamls):
        folder = data_yaml.parent
        images = sorted(p.name for p in (folder / "images").iterdir())
        assert images == [f"{i:06d}.png" for i in (1, 2, 3)]
        for image_id, _path, _frame, rgb, labels in truth:
            png = cv2.imread(str(folder / "images" / f"{image_id:06d}.png"), cv2.IMREAD_COLOR)
            assert np.array_equal(png[:, :, ::-1], rgb[rate_index])  # byte for byte
            boxes, class_ids = read_yolo_labels(folder / "labels" / f"{image_id:06d}.txt",
                                                96, 72)
            assert boxes.shape == labels["bbox"].shape
            np.testing.assert_allclose(boxes, labels["bbox"], atol=1e-3)
            assert np.array_equal(class_ids, labels["class_id"])
        empty = [t[0] for t in truth if len(t[4]["bbox"]) == 0]
        for image_id in empty:
            assert (folder / "labels" / f"{image_id:06d}.txt").read_text() == ""


def test_yolo_data_yaml_is_trainable_by_ultralytics(dataset, tmp_path):
    from ultralytics.data.dataset import YOLODataset  # noqa: PLC0415
    from ultralytics.data.utils import check_det_dataset  # noqa: PLC0415

    data_yaml = export_yolo(dataset, tmp_path / "yolo", rates=[50])[0]
    data = check_det_dataset(str(data_yaml))
    assert data["names"] == {0: "person", 1: "bicycle", 2: "car", 3: "motorcycle"}
    assert data["nc"] == 4
    assert str(data["path"]) == str(data_yaml.parent.resolve())
    ds = YOLODataset(img_path=data["train"], data=data, task="detect", augment=False,
                     imgsz=96, batch_size=1, rect=False, cache=False)
    truth = shard_truth(dataset)
    assert [len(label["cls"]) for label in ds.labels] == [len(t[4]["bbox"]) for t in truth]
    # ultralytics' own reading of the label files: normalised centre x, centre y, width, height of
    # the shard's xyxy pixel-edge boxes (a writer and reader that both swapped x and y passed
    # the round trip above)
    for label, (_, _, _, _, labels) in zip(ds.labels, truth):
        x1, y1, x2, y2 = labels["bbox"].T.astype(np.float64)
        expected = np.stack([(x1 + x2) / 2 / 96, (y1 + y2) / 2 / 72, (x2 - x1) / 96, (y2 - y1) / 72], axis=1)
        np.testing.assert_allclose(label["bboxes"], expected.reshape(-1, 4), atol=1e-5)
        assert label["cls"].ravel().tolist() == labels["class_id"].tolist()


def test_coco_round_trip(dataset, tmp_path):
    from pycocotools.coco import COCO  # noqa: PLC0415

    truth = shard_truth(dataset)
    out = tmp_path / "coco"
    paths = export_coco(dataset, out)
    assert paths == [out / "rate_0.json", out / "rate_50.json"]
    crowd_seen = 0
    for rate_index, (path, token) in enumerate(zip(paths, ("0", "50"))):
        coco = COCO(str(path))
        assert sorted(coco.getImgIds()) == [1, 2, 3]
        assert [c["name"] for c in coco.loadCats(coco.getCatIds())] == \
            ["person", "bicycle", "car", "motorcycle"]
        payload = json.loads(path.read_text())
        assert [image["id"] for image in payload["images"]] == [1, 2, 3]
        ids = [a["id"] for a in payload["annotations"]]
        assert ids == list(range(1, len(ids) + 1))
        for image_id, shard, frame, rgb, labels in truth:
            image = coco.loadImgs(image_id)[0]
            assert image["file_name"] == f"rate_{token}/images/{image_id:06d}.png"
            assert (image["width"], image["height"], image["frame"]) == (96, 72, frame)
            assert image["shard"] == shard.name
            png = cv2.imread(str(out / image["file_name"]), cv2.IMREAD_COLOR)
            assert np.array_equal(png[:, :, ::-1], rgb[rate_index])
            every = coco.loadAnns(coco.getAnnIds(imgIds=[image_id]))
            anns = [ann for ann in every if not ann["iscrowd"]]
            assert len(anns) == len(labels["bbox"])
            with open_shard(shard) as handle:  # ignore regions: crowd boxes after the labels
                regions = read_frame_ignore(handle, frame)
            crowd = every[len(anns):]
            assert [ann["instance_id"] for ann in crowd] == regions["instance_id"].tolist()
            for ann, box, class_id in zip(crowd, regions["bbox"], regions["class_id"]):
                x, y, w, h = ann["bbox"]
                np.testing.assert_allclose([x, y, x + w, y + h], box, atol=1e-3)
                assert (ann["category_id"], ann["iscrowd"], ann["ignore"]) == (class_id, 1, 1)
            crowd_seen += len(crowd)
            for ann, box, class_id, vis, trunc, inst, cov in zip(
                    anns, labels["bbox"], labels["class_id"], labels["visible_fraction"],
                    labels["truncation"], labels["instance_id"],
                    labels["rain_coverage"][rate_index]):
                x, y, w, h = ann["bbox"]
                np.testing.assert_allclose([x, y, x + w, y + h], box, atol=1e-3)
                assert ann["area"] == pytest.approx(w * h)
                assert ann["category_id"] == class_id and ann["iscrowd"] == 0
                assert ann["visible_fraction"] == pytest.approx(float(vis))
                assert ann["truncation"] == pytest.approx(float(trunc))
                assert ann["instance_id"] == inst
                assert ann["rain_coverage"] == pytest.approx(float(cov))
    assert crowd_seen > 0  # at 96x72 some actors are too small to label


def test_rate_selection_and_errors(dataset, tmp_path):
    assert export_coco(dataset, tmp_path / "a", rates=[50.0], images=False) == \
        [tmp_path / "a" / "rate_50.json"]
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == ["rate_50.json"]
    with pytest.raises(ExportError, match=r"rate 25 mm/h is not in the dataset"):
        export_yolo(dataset, tmp_path / "b", rates=[0, 25])
    with pytest.raises(ExportError, match="rate 25"):
        write_videos(dataset, tmp_path / "b", rates=[25])
    with pytest.raises(ExportError, match="image_format"):
        export_yolo(dataset, tmp_path / "c", image_format="bmp")
    with pytest.raises(ExportError, match="not empty"):
        export_yolo(dataset, tmp_path / "a")
    with pytest.raises(ExportError, match="not empty"):
        export_coco(dataset, tmp_path / "a")
    (tmp_path / "a" / "keep.txt").write_text("mine")
    export_yolo(dataset, tmp_path / "a", rates=[50], overwrite=True)
    export_coco(dataset, tmp_path / "a", rates=[50], overwrite=True)  # both share one out_dir
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == \
        ["keep.txt", "rate_50", "rate_50.json"]
    assert sorted(p.name for p in (tmp_path / "a" / "rate_50").iterdir()) == \
        ["data.yaml", "images", "labels"]


def test_read_yolo_labels_errors(tmp_path):
    path = tmp_path / "bad.txt"
    path.write_text("0 0.5 0.5 0.1\n")
    with pytest.raises(ExportError, match=r"bad.txt:1"):
        read_yolo_labels(path, 10, 10)
    path.write_text("")
    boxes, class_ids = read_yolo_labels(path, 10, 10)
    assert boxes.shape == (0, 4) and class_ids.shape == (0,)


def read_video(path):
    capture = cv2.VideoCapture(str(path))
    assert capture.isOpened()
    frames = []
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        frames.append(frame)
    capture.release()
    return frames


def test_video_round_trip(dataset, tmp_path):
    truth = shard_truth(dataset)
    paths = write_videos(dataset, tmp_path / "video")
    assert paths == [tmp_path / "video" / "rate_0.mp4", tmp_path / "video" / "rate_50.mp4"]
    assert sorted(p.name for p in (tmp_path / "video").iterdir()) == ["rate_0.mp4", "rate_50.mp4"]
    for path in paths:
        frames = read_video(path)
        assert len(frames) == len(truth) == 3
        assert all(frame.shape == (72, 96, 3) for frame in frames)
    # Without boxes the frames are the shard's images up to mp4v compression.
    plain = write_videos(dataset, tmp_path / "plain", rates=[0], boxes=False, fps=5)
    frames = read_video(plain[0])
    assert cv2.VideoCapture(str(plain[0])).get(cv2.CAP_PROP_FPS) == pytest.approx(5)
    for frame, (_id, _path, _frame, rgb, _labels) in zip(frames, truth):
        error = np.abs(frame[:, :, ::-1].astype(int) - rgb[0].astype(int)).mean()
        assert error < 12
    with pytest.raises(ExportError, match="already exists"):
        write_videos(dataset, tmp_path / "plain", rates=[0])


def test_video_codec_unavailable(dataset, tmp_path, monkeypatch):
    class Closed:
        def __init__(self, *args):
            pass

        def isOpened(self):
            return False

        def release(self):
            pass

    monkeypatch.setattr(video_module.cv2, "VideoWriter", Closed)
    with pytest.raises(ExportError, match="mp4v"):
        write_videos(dataset, tmp_path / "v", rates=[0])
    assert list((tmp_path / "v").iterdir()) == []
