"""Observation discretisation: band edges, validation, synthesize -> level round trips."""

import numpy as np
import pytest

from hrc_ros.core.decision.observation import (closest_distance, distance_level,
                                               synthesize_joint_velocities, synthesize_skeleton,
                                               velocity_level, window_level)

T = (0.3, 0.8)
R = (0.2, 0.6, 1.2)
SEEDS = range(300)


# -- velocity level ----------------------------------------------------------------------
@pytest.mark.parametrize('speeds, level', [
    ([0.0], 1), ([0.2999], 1), ([0.3], 2), ([-0.3], 2), ([0.7999], 2), ([0.8], 3),
    ([5.0], 3), ([-0.5, 0.5], 2), ([0.1, -0.1, 1.0], 2), ([0.2, 0.4], 2), ([0.1, 0.4], 1),
])
def test_velocity_level_bands_use_mean_absolute_value(speeds, level):
    assert velocity_level(speeds, T) == level


def test_velocity_level_accepts_numpy_and_other_thresholds():
    assert velocity_level(np.array([1.0, -1.0, 1.0]), (1.5, 2.0)) == 1
    assert velocity_level(np.array([[1.0, 2.0], [2.0, 3.0]]), (1.0, 2.0)) == 3


@pytest.mark.parametrize('speeds, thresholds, field', [
    ([], T, 'speeds'), ([np.nan], T, 'speeds'), ([np.inf, 0.1], T, 'speeds'),
    (['fast'], T, 'speeds'), ([0.1], (0.8, 0.3), 'thresholds'), ([0.1], (0.3, 0.3), 'thresholds'),
    ([0.1], (0.0, 0.8), 'thresholds'), ([0.1], (-1.0, 0.8), 'thresholds'),
    ([0.1], (0.3,), 'thresholds'), ([0.1], (0.3, np.nan), 'thresholds'),
])
def test_velocity_level_rejects_bad_input(speeds, thresholds, field):
    with pytest.raises(ValueError, match=field):
        velocity_level(speeds, thresholds)


# -- window ------------------------------------------------------------------------------
@pytest.mark.parametrize('levels, level', [
    ([1], 1), ([1, 1, 2], 1), ([1, 2], 2), ([3, 1, 1, 3], 3), ([2, 2, 3, 3, 1], 3),
    ([1, 2, 2, 3], 2), (np.array([2, 1, 1]), 1), ((3, 3, 3), 3),
])
def test_window_level_is_majority_with_ties_to_higher(levels, level):
    assert window_level(levels) == level


def test_window_level_is_independent_of_window_length():
    assert window_level([2, 3, 2] * 17) == window_level([2, 3, 2]) == 2


@pytest.mark.parametrize('levels', [[], np.array([], dtype=int), [1.5], [-1], [True]])
def test_window_level_rejects_bad_input(levels):
    with pytest.raises(ValueError, match='levels'):
        window_level(levels)


# -- distance level ----------------------------------------------------------------------
@pytest.mark.parametrize('r, d', [
    (0.0, 0), (0.1999, 0), (0.2, 1), (0.5999, 1), (0.6, 2), (1.1999, 2), (1.2, 3), (9.0, 3),
])
def test_distance_level_band_edges(r, d):
    assert distance_level([[r, 0.0, 0.0]], (0, 0, 0), R) == d
    # The same along another axis and from a shifted robot reference point.
    p = np.array([1.0, -2.0, 0.0])  # z = r exactly: no rounding at the edges
    assert distance_level([p + [0.0, 0.0, r]], p, R) == d


def test_distance_level_uses_the_closest_keypoint():
    keypoints = [[3.0, 0.0, 0.0], [0.0, 0.5, 0.0], [0.0, 0.0, 2.0]]
    assert closest_distance(keypoints, (0, 0, 0)) == pytest.approx(0.5)
    assert distance_level(keypoints, (0, 0, 0), R) == 1


@pytest.mark.parametrize('keypoints, point, radii, field', [
    (np.zeros((0, 3)), (0, 0, 0), R, 'keypoints'), (np.zeros((4, 2)), (0, 0, 0), R, 'keypoints'),
    (np.zeros(3), (0, 0, 0), R, 'keypoints'), ([[np.nan, 0, 0]], (0, 0, 0), R, 'keypoints'),
    (np.ones((2, 3)), (0, 0), R, 'robot_point'), (np.ones((2, 3)), (0, np.inf, 0), R,
                                                  'robot_point'),
    (np.ones((2, 3)), (0, 0, 0), (0.6, 0.2, 1.2), 'radii'),
    (np.ones((2, 3)), (0, 0, 0), (0.0, 0.2, 1.2), 'radii'),
    (np.ones((2, 3)), (0, 0, 0), (0.2, 0.6), 'radii'),
])
def test_distance_level_rejects_bad_input(keypoints, point, radii, field):
    with pytest.raises(ValueError, match=field):
        distance_level(keypoints, point, radii)


# -- synthesis round trips ---------------------------------------------------------------
@pytest.mark.parametrize('n_joints', [1, 6, 14])
@pytest.mark.parametrize('level', [1, 2, 3])
def test_synthesized_velocities_have_their_level(level, n_joints):
    for seed in SEEDS:
        v = synthesize_joint_velocities(level, n_joints, T, np.random.default_rng(seed))
        assert v.shape == (n_joints,)
        assert velocity_level(v, T) == level
        assert np.mean(np.abs(v)) < 2 * T[1]


def test_synthesized_velocities_are_signed_and_spread():
    v = synthesize_joint_velocities(2, 200, T, np.random.default_rng(1))
    assert (v < 0).any() and (v > 0).any()
    assert np.std(np.abs(v)) > 0.05
    assert np.abs(v).max() > T[0] * 0.9 * 1.2  # some joints leave the mean's band


def test_synthesis_is_reproducible_by_seed():
    a = synthesize_joint_velocities(3, 6, T, np.random.default_rng(7))
    b = synthesize_joint_velocities(3, 6, T, np.random.default_rng(7))
    np.testing.assert_array_equal(a, b)
    a = synthesize_skeleton(2, R, (0, 0, 0), np.random.default_rng(7))
    b = synthesize_skeleton(2, R, (0, 0, 0), np.random.default_rng(7))
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize('d', [0, 1, 2, 3])
def test_synthesized_skeletons_have_their_distance_level(d):
    point = np.array([0.4, -0.3, 0.9])
    edges = (0.0, *R, R[2] + 1.0)
    for seed in SEEDS:
        rng = np.random.default_rng(seed)
        n = 1 + seed % 9
        keypoints = synthesize_skeleton(d, R, point, rng, n_keypoints=n)
        assert keypoints.shape == (n, 3)
        assert distance_level(keypoints, point, R) == d
        assert edges[d] < closest_distance(keypoints, point) < edges[d + 1]


@pytest.mark.parametrize('call, field', [
    (lambda: synthesize_joint_velocities(0, 6, T), 'level'),
    (lambda: synthesize_joint_velocities(4, 6, T), 'level'),
    (lambda: synthesize_joint_velocities(2, 0, T), 'n_joints'),
    (lambda: synthesize_joint_velocities(2, 6, (0.8, 0.3)), 'thresholds'),
    (lambda: synthesize_skeleton(4, R), 'd'),
    (lambda: synthesize_skeleton(-1, R), 'd'),
    (lambda: synthesize_skeleton(1, R, n_keypoints=0), 'n_keypoints'),
    (lambda: synthesize_skeleton(1, (1.0, 0.5, 2.0)), 'radii'),
])
def test_synthesis_rejects_bad_input(call, field):
    with pytest.raises(ValueError, match=field):
        call()


# -- several features --------------------------------------------------------------------
def _column_stochastic(rng, levels):
    m = rng.uniform(0.05, 1.0, size=(levels, 9))
    return m / m.sum(axis=0)
