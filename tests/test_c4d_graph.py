"""Scene graph: the strided sliding window of MonST3R's video default, symmetric, and its errors."""

import numpy as np
import pytest

from c4d_core.config import load_config
from c4d_core.errors import UserError
from c4d_pipeline.scene_graph import (frame_neighbours, graph_from_config, is_connected,
                                      strided_window_pairs, window_offsets)


def test_default_offsets_are_1_3_5_7_9():
    assert window_offsets(5, 2, 1) == [1, 3, 5, 7, 9]


@pytest.mark.parametrize("frames,unique", [(30, 125), (50, 225), (90, 425)])
def test_pair_counts_match_5n_minus_25(frames, unique):
    edges = strided_window_pairs(frames)
    assert edges.shape == (2 * unique, 2)
    assert len({tuple(e) for e in edges}) == 2 * unique  # no duplicates


def test_symmetric_second_half_reverses_first_half():
    edges = strided_window_pairs(12, window=3, stride=2)
    half = len(edges) // 2
    np.testing.assert_array_equal(edges[half:], edges[:half, ::-1])
    assert (edges[:half, 0] < edges[:half, 1]).all()
    assert set(np.unique(edges[:half, 1] - edges[:half, 0])) == {1, 3, 5}


def test_short_video_keeps_only_fitting_offsets():
    edges = strided_window_pairs(4, symmetric=False)
    assert [tuple(e) for e in edges] == [(0, 1), (0, 3), (1, 2), (2, 3)]


def test_too_short_or_disconnected_graph_is_a_user_error():
    with pytest.raises(UserError, match="at least 2 frames"):
        strided_window_pairs(1)
    with pytest.raises(UserError, match="does not connect"):
        strided_window_pairs(6, window=2, stride=2, start=2)  # offsets 2, 4: odd/even split
    with pytest.raises(UserError):
        window_offsets(0, 2)


def test_connectivity_and_neighbours():
    assert is_connected(3, [(0, 1), (1, 2)]) and not is_connected(3, [(0, 1)])
    neigh = frame_neighbours(strided_window_pairs(6, window=2, stride=2), 6)
    assert neigh[0] == [1, 3] and neigh[3] == [0, 2, 4]


def test_graph_from_default_config():
    cfg = load_config("c4d", "default")
    assert len(graph_from_config(30, cfg.graph)) == 250
