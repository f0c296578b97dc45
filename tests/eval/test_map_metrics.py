import numpy as np
import pytest

from kimera_multi_py.eval.metrics import (
    object_precision_recall,
    occupancy_f1,
    occupancy_precision_recall,
    semantic_iou_per_class,
    semantic_miou,
)


def test_occupancy_f1_scores_only_cells_both_know():
    gt = np.array([0, 0, 1, 2, 2, 0, -1, 3])
    pred = np.array([0, 1, 1, 2, 0, -1, 5, 3])
    s = occupancy_precision_recall(pred, gt)
    # scored cells: 0..4 and 7 -> tp = 3 (cells 2, 3, 7), fp = 1 (cell 1), fn = 1 (cell 4)
    assert (s["tp"], s["fp"], s["fn"], s["cells"]) == (3, 1, 1, 6)
    assert s["precision"] == pytest.approx(0.75) and s["recall"] == pytest.approx(0.75)
    assert occupancy_f1(pred, gt) == pytest.approx(0.75)
    assert occupancy_f1(gt, gt) == 1.0
    assert occupancy_f1(np.full(3, -1), np.array([1, 0, 2])) == 0.0
    with pytest.raises(ValueError):
        occupancy_f1(pred[:-1], gt)


def test_semantic_miou_over_classes_present():
    gt = np.array([1, 1, 1, 2, 2, 0, 0, -1, 3])
    pred = np.array([1, 1, 2, 2, 2, 0, 1, 4, -1])
    # class 1: inter 2, union 4 (cells 0, 1, 2, 6); class 2: inter 2, union 3; class 3 unscored
    per = semantic_iou_per_class(pred, gt)
    assert per == {1: pytest.approx(0.5), 2: pytest.approx(2 / 3)}
    assert semantic_miou(pred, gt) == pytest.approx((0.5 + 2 / 3) / 2)
    assert semantic_miou(gt, gt) == 1.0
    assert semantic_miou(pred, gt, classes=[4]) == 0.0  # predicted only where gt is unknown


def test_object_precision_recall_matches_one_to_one_within_the_gate():
    gt_cls = np.array([5, 5, 6])
    gt_xyz = np.array([[0.0, 0, 0], [1.0, 0, 0], [5.0, 5, 0]])
    pred_cls = np.array([5, 5, 5, 6, 7])
    pred_xyz = np.array([[0.1, 0, 0], [0.2, 0, 0], [1.3, 0, 0], [5.0, 5.6, 0], [0.0, 0, 0]])
    s = object_precision_recall(pred_cls, pred_xyz, gt_cls, gt_xyz, max_distance=0.5)
    # chairs: (0.1 -> 0) and (1.3 -> 1) are the optimal pair set; the table is 0.6 m off
    assert s["matches"] == 2
    assert s["precision"] == pytest.approx(2 / 5) and s["recall"] == pytest.approx(2 / 3)
    assert s["mean_error"] == pytest.approx((0.1 + 0.3) / 2)
    perfect = object_precision_recall(gt_cls, gt_xyz, gt_cls, gt_xyz)
    assert perfect["precision"] == perfect["recall"] == 1.0 and perfect["mean_error"] == 0.0
    empty = object_precision_recall(np.zeros(0), np.zeros((0, 3)), gt_cls, gt_xyz)
    assert empty["precision"] == 0.0 and empty["recall"] == 0.0 and np.isnan(empty["mean_error"])
