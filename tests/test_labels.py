"""Pure label functions on hand-made instance maps with exactly known answers."""

import numpy as np
import pytest

from rainbench.gen import labels as lb


def test_tight_boxes_are_pixel_edge():
    inst = np.full((10, 12), -1, np.int32)
    inst[2:5, 3:7] = 0  # rows 2..4, columns 3..6
    inst[8, 11] = 2
    counts, boxes = lb.tight_boxes(inst, 3)
    assert counts.tolist() == [12, 0, 1]
    assert boxes[0].tolist() == [3, 2, 7, 5]
    assert np.isnan(boxes[1]).all()
    assert boxes[2].tolist() == [11, 8, 12, 9]


def test_tight_boxes_rejects_float_maps():
    with pytest.raises(ValueError, match=r"instance_map: expected \(H, W\) integer"):
        lb.tight_boxes(np.zeros((4, 4), np.float32), 1)


def test_alone_statistics_counts_outside_pixels_as_truncated():
    width, height, margins = 8, 6, (2, 3)
    alone = np.full((height + 6, width + 4), -1, np.int32)
    # Actor 0: 4 columns, of which the 2 leftmost are left of the image.
    alone[5:7, 0:4] = 0
    in_image, total, amodal = lb.alone_statistics(alone, (0, 0), margins, (width, height), 1)
    assert in_image.tolist() == [4] and total.tolist() == [8]
    assert amodal[0].tolist() == [0, 2, 2, 4]  # image coordinates, clipped to the image
    # The same from a window of the canvas holding the actor.
    window = lb.union_window([(0, 5, 4, 7)], (width + 4, height + 6))
    x0, y0, x1, y1 = window
    windowed = lb.alone_statistics(alone[y0:y1, x0:x1], (x0, y0), margins, (width, height), 1)
    for got, expected in zip(windowed, (in_image, total, amodal)):
        np.testing.assert_array_equal(got, expected)


def test_alone_statistics_checks_the_window():
    with pytest.raises(ValueError, match=r"alone_map: expected a window inside the 12x12 canvas"):
        lb.alone_statistics(np.zeros((5, 5), np.int32), (10, 0), (2, 3), (8, 6), 1)


def test_make_labels_occlusion_truncation_and_filters():
    classes = np.array([2, 0, 1], np.int32)
    visible_counts = np.array([50, 100, 5])
    visible_boxes = np.array([[0, 0, 10, 10], [20, 20, 30, 40], [0, 0, 2, 3]], np.float32)
    alone_in = np.array([100, 100, 5])
    alone_total = np.array([100, 400, 5])
    amodal = np.array([[0, 0, 20, 10], [20, 20, 30, 40], [0, 0, 2, 3]], np.float32)
    labels = lb.make_labels(visible_counts, visible_boxes, alone_in, alone_total, amodal,
                            classes, lb.LabelFilter(min_box_height=8, min_visible_fraction=0.1,
                                                    min_visible_pixels=20))
    assert labels.instance_id.tolist() == [0, 1]  # instance 2 is too small
    assert labels.class_id.tolist() == [2, 0]
    np.testing.assert_allclose(labels.visible_fraction, [0.5, 1.0])
    np.testing.assert_allclose(labels.truncation, [0.0, 0.75])
    assert labels.bbox_amodal[0].tolist() == [0, 0, 20, 10]


def test_visible_actors_the_filter_leaves_out_become_ignore_regions():
    classes = np.array([2, 0, 0, 1], np.int32)
    visible_counts = np.array([50, 12, 30, 0])  # 1: too few pixels, 2: too hidden, 3: unseen
    visible_boxes = np.array([[0, 0, 10, 10], [20, 20, 23, 26], [40, 10, 44, 20],
                              [np.nan] * 4], np.float32)
    alone_in = np.array([100, 12, 400, 50])
    alone_total = np.array([100, 12, 400, 50])
    amodal = np.array([[0, 0, 20, 10], [20, 19, 23, 26], [40, 0, 50, 40], [60, 0, 70, 10]],
                      np.float32)
    labels = lb.make_labels(visible_counts, visible_boxes, alone_in, alone_total, amodal, classes,
                            lb.LabelFilter(min_box_height=8, min_visible_fraction=0.1,
                                           min_visible_pixels=20))
    assert labels.instance_id.tolist() == [0] and len(labels) == 1
    assert labels.ignore_instance_id.tolist() == [1, 2]  # the unseen actor 3 is neither
    assert labels.ignore_class_id.tolist() == [0, 0]
    # the box enclosing what is seen and the whole unoccluded actor
    assert labels.ignore_bbox.tolist() == [[20, 19, 23, 26], [40, 0, 50, 40]]
    assert labels.ignore_bbox.dtype == np.float32


def test_label_filter_rejects_bad_values():
    with pytest.raises(ValueError, match=r"min_visible_fraction: expected a number in 0\.\.1, got 1\.5"):
        lb.LabelFilter(min_visible_fraction=1.5)


def test_group_disjoint_separates_overlapping_boxes():
    boxes = {0: (0, 0, 10, 10), 1: (5, 5, 15, 15), 2: (20, 0, 30, 10), 3: (8, 8, 12, 12)}
    groups = lb.group_disjoint(boxes)
    assert groups[0] == [0, 2]
    for group in groups:
        for a in group:
            for b in group:
                if a < b:
                    ba, bb = boxes[a], boxes[b]
                    assert ba[2] <= bb[0] or bb[2] <= ba[0] or ba[3] <= bb[1] or bb[3] <= ba[1]
    assert sorted(i for g in groups for i in g) == [0, 1, 2, 3]
