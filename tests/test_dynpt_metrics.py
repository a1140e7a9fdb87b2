"""TAP-Vid metrics and D-ACC against hand-computed cases."""

import numpy as np
import pytest

from dynpt.metrics import (THRESHOLDS_PX, average_precision, dynamic_accuracy, paired_bootstrap_interval,
                           roc_auc, tapvid_metrics)

KEYS = {"occlusion_accuracy", "average_jaccard", "average_pts_within_thresh"} | {
    f"{name}_{d}" for name in ("pts_within", "jaccard") for d in THRESHOLDS_PX
}


def _one_track(T=5, query_t=1):
    """One video, one track moving right by 3 px a frame, visible everywhere."""
    gt = np.stack([np.arange(T) * 3.0 + 10, np.full(T, 20.0)], axis=-1)[None, None]  # (1,1,T,2)
    occ = np.zeros((1, 1, T), bool)
    query = np.array([[[query_t, gt[0, 0, query_t, 1], gt[0, 0, query_t, 0]]]])
    return query, occ, gt


@pytest.mark.parametrize("mode", ["first", "strided"])
def test_perfect_prediction_scores_one(mode):
    query, occ, gt = _one_track()
    out = tapvid_metrics(query, occ, gt, occ, gt.copy(), mode)
    assert set(out) == KEYS
    for key, value in out.items():
        assert value.shape == (1,)
        assert value[0] == pytest.approx(1.0), key


def test_all_occluded_gives_nan_like_the_reference():
    query, occ, gt = _one_track()
    occ[:] = True
    with np.errstate(invalid="ignore", divide="ignore"):
        both_occ = tapvid_metrics(query, occ, gt, occ, gt, "first")
        pred_vis = tapvid_metrics(query, occ, gt, np.zeros_like(occ), gt, "first")
    assert both_occ["occlusion_accuracy"][0] == 1.0
    assert np.isnan(both_occ["average_jaccard"][0]) and np.isnan(both_occ["pts_within_1"][0])
    assert pred_vis["occlusion_accuracy"][0] == 0.0
    assert pred_vis["jaccard_4"][0] == 0.0 and np.isnan(pred_vis["pts_within_4"][0])


def test_threshold_is_strict():
    """Off by exactly 2 px: inside 4, 8, 16; outside 1 and 2 (strict <)."""
    query, occ, gt = _one_track()
    pred = gt.copy()
    pred[..., 0] += 2.0
    out = tapvid_metrics(query, occ, gt, occ, pred, "strided")
    assert [out[f"pts_within_{d}"][0] for d in THRESHOLDS_PX] == [0, 0, 1, 1, 1]
    # A far but predicted-visible point is both a miss and a false positive: 0 / (4 + 4).
    assert out["jaccard_2"][0] == 0.0
    assert out["average_pts_within_thresh"][0] == pytest.approx(0.6)
    assert out["average_jaccard"][0] == pytest.approx(0.6)


def test_which_frames_count():
    """Query at t=2 of T=5: 'first' scores t=3,4; 'strided' scores t=0,1,3,4; t=2 never."""
    query, occ, gt = _one_track(T=5, query_t=2)
    pred = gt.copy()
    pred[0, 0, 2] += 100.0  # wrong at the query frame: never counted
    pred[0, 0, 0] += 100.0  # wrong before the query frame: counted only in 'strided'
    first = tapvid_metrics(query, occ, gt, occ, pred, "first")
    strided = tapvid_metrics(query, occ, gt, occ, pred, "strided")
    assert first["pts_within_16"][0] == 1.0
    assert strided["pts_within_16"][0] == pytest.approx(3 / 4)
    # 3 TP, 1 FN that is also an FP: 3 / (4 + 1).
    assert strided["jaccard_16"][0] == pytest.approx(3 / 5)


def test_occlusion_accuracy_and_jaccard_counts():
    """Hand count: 2 tracks, T=4, query t=0, 'first' -> 6 evaluated pairs."""
    T = 4
    gt = np.zeros((1, 2, T, 2))
    gt_occ = np.array([[[0, 0, 1, 0], [0, 0, 0, 1]]], bool)
    pred_occ = np.array([[[0, 1, 0, 0], [0, 0, 0, 0]]], bool)
    pred = gt.copy()
    pred[0, 1, 1] = [0.0, 5.0]  # 5 px off: within 8 and 16 only
    query = np.zeros((1, 2, 3))
    out = tapvid_metrics(query, gt_occ, gt, pred_occ, pred, "first")
    # Agreement on t=1..3: track 0 -> t3 only; track 1 -> t1,t2 -> 3 of 6.
    assert out["occlusion_accuracy"][0] == pytest.approx(3 / 6)
    # GT visible evaluated: (0,1),(0,3),(1,1),(1,2) -> 4. Within 4 px: 3 of them.
    assert out["pts_within_4"][0] == pytest.approx(3 / 4)
    # delta 4: TP=(0,3),(1,2); FP=(0,2) occluded, (1,3) occluded, (1,1) far -> 2 / (4 + 3).
    assert out["jaccard_4"][0] == pytest.approx(2 / 7)
    # delta 8: TP=(0,3),(1,1),(1,2); FP=(0,2),(1,3) -> 3 / 6.
    assert out["jaccard_8"][0] == pytest.approx(3 / 6)


def test_per_video_not_pooled_and_trackwise_shapes():
    query, occ, gt = _one_track()
    bad = gt.copy()
    bad[..., 0] += 50.0
    q2, o2, g2 = (np.concatenate([a, a]) for a in (query, occ, gt))
    pred = np.concatenate([gt, bad])
    out = tapvid_metrics(q2, o2, g2, o2, pred, "first")
    np.testing.assert_allclose(out["average_pts_within_thresh"], [1.0, 0.0])
    tw = tapvid_metrics(q2, o2, g2, o2, pred, "first", get_trackwise_metrics=True)
    assert tw["average_jaccard"].shape == (2, 1)


def test_query_time_rounds_half_to_even_and_float_occlusion():
    query, occ, gt = _one_track(T=6)
    pred = gt.copy()
    pred[0, 0, 3] += 100.0
    query[..., 0] = 2.5  # rounds to 2: t=3 is scored in 'first'
    out = tapvid_metrics(query, occ, gt, occ.astype(np.float32), pred, "first")
    assert out["pts_within_1"][0] == pytest.approx(2 / 3)
    query[..., 0] = 3.5  # rounds to 4: t=3 is not scored
    out = tapvid_metrics(query, occ, gt, occ, pred, "first")
    assert out["pts_within_1"][0] == 1.0
    with pytest.raises(ValueError):
        tapvid_metrics(query, occ, gt, occ, pred, "middle")


def test_dynamic_accuracy_hand_cases():
    gt = np.array([[1, 1, 0, 0], [0, 0, 0, 1]], bool)
    pred = np.array([[1, 0, 0, 1], [0, 0, 0, 1]], bool)
    assert dynamic_accuracy(pred, gt) == pytest.approx(6 / 8)
    valid = np.array([[1, 0, 1, 0], [1, 1, 1, 1]], bool)
    assert dynamic_accuracy(pred, gt, valid) == 1.0
    assert np.isnan(dynamic_accuracy(pred, gt, np.zeros_like(valid)))
    assert dynamic_accuracy(~gt, gt) == 0.0


def test_ranking_metrics_hand_cases():
    scores, labels = [0.9, 0.8, 0.7, 0.6], [True, False, True, False]
    # recall 0.5 at precision 1, then recall 1 at precision 2/3
    assert average_precision(scores, labels) == pytest.approx(0.5 * 1 + 0.5 * 2 / 3)
    # positive-negative pairs ordered right: (0.9,0.8), (0.9,0.6), (0.7,0.6) of 4
    assert roc_auc(scores, labels) == pytest.approx(3 / 4)
    assert average_precision([0.2, 0.9, 0.1], [False, True, False]) == 1.0
    assert roc_auc(np.array([[0.2, 0.9], [0.1, 0.8]]), np.array([[0, 1], [0, 1]])) == 1.0


def test_ranking_metrics_ties_and_errors():
    scores, labels = [0.5, 0.5, 0.1], [True, False, True]
    # the tied pair is one threshold: recall 0.5 at precision 1/2, then recall 1 at 2/3
    assert average_precision(scores, labels) == pytest.approx(0.5 * 0.5 + 0.5 * 2 / 3)
    assert roc_auc(scores, labels) == pytest.approx((0.5 + 0.0) / 2)  # a tie counts one half
    with pytest.raises(ValueError, match="both positive and negative"):
        average_precision([0.1, 0.2], [False, False])
    with pytest.raises(ValueError, match="differ in size"):
        roc_auc([0.1, 0.2], [True])


def test_paired_bootstrap_interval_hand_cases():
    total = np.array([10, 10, 10, 10])
    # The same counts for both methods: every resample gives a difference of exactly 0.
    assert paired_bootstrap_interval([9, 8, 7, 9], total, [9, 8, 7, 9], total) == (0.0, 0.0)
    # A one point (of 10) better on every video: +0.1 whatever the videos drawn.
    low, high = paired_bootstrap_interval([9, 8, 7, 9], total, [8, 7, 6, 8], total)
    assert low == pytest.approx(0.1) and high == pytest.approx(0.1)
    # A better on two videos, worse on two: the interval spans the per-video differences' range
    # only partly, holds the pooled difference (0) and is the same for the same seed.
    a, b = [10, 10, 5, 5], [5, 5, 10, 10]
    low, high = paired_bootstrap_interval(a, total, b, total)
    assert -0.5 <= low < 0 < high <= 0.5
    assert (low, high) == paired_bootstrap_interval(a, total, b, total)
    assert paired_bootstrap_interval(a, total, b, total, level=0.5)[1] < high  # narrower
    with pytest.raises(ValueError, match="per-video counts"):
        paired_bootstrap_interval([1, 2], [2, 2], [1], [2])
