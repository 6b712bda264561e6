"""The body-tracking input without DDS: frame transform, arm angles, body selection with
hysteresis, velocity derivation, jump rejection and the synthetic tracker (core.cell.tracking).

Bodies are built with `SyntheticBody` (joints at known angles and a known closest distance) and
then moved, duplicated, swapped or broken frame by frame, as a tracker's bad streams would.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from hrc_ros.core.decision.observation import (DEFAULT_SAFETY_RADII, closest_distance,
                                               distance_band, distance_level)
from hrc_ros.core.protocol import InputError, Stamp
from hrc_ros.core.cell.tracking import (ANGLE_RANGE, JOINT_INDEX, JUMP_SLACK, K4ABT_JOINTS,
                                        BodyFrame, BodyTracking, RigidTransform, SyntheticBody,
                                        arm_angles, joint_indices, split_marker_id)

DT = 1 / 30                                  # the Azure Kinect's frame period
CAMERA = RigidTransform.from_parameters(     # 2.5 m ahead, 1.6 m up, looking back and down
    [2.5, 0.0, 1.6], [0.579228, 0.579228, -0.40558, -0.40558])


def body(rho: float, direction=(1.0, 0.0), angles=(0.6, 0.6, 1.2, 1.2, 0.7, 0.7)) -> np.ndarray:
    """A standing body (robot frame) whose closest joint is rho from the origin."""
    synthetic = SyntheticBody(direction=list(direction) + [0.0])
    return synthetic.place(synthetic.local_joints(angles), rho)


def frame(stamp: float, **bodies) -> BodyFrame:
    """A frame of bodies given in the robot frame (b1=..., b2=...), seen from CAMERA."""
    to_camera = CAMERA.inverse()
    return BodyFrame(stamp, {int(k[1:]): to_camera.apply(v) for k, v in bodies.items()})


def tracker(**kwargs) -> BodyTracking:
    return BodyTracking(CAMERA, **kwargs)


# -- transform, angles, ids -------------------------------------------------------------------
def test_rigid_transform_rotates_then_translates_and_inverts():
    quarter = RigidTransform.from_parameters([1.0, 2.0, 3.0],
                                             [0.0, 0.0, math.sin(math.pi / 4),
                                              math.cos(math.pi / 4)])   # 90 deg about z
    np.testing.assert_allclose(quarter.apply([[1.0, 0.0, 0.0], [0.0, 1.0, 0.5]]),
                               [[1.0, 3.0, 3.0], [0.0, 2.0, 3.5]], atol=1e-12)
    points = np.random.default_rng(0).normal(size=(10, 3))
    np.testing.assert_allclose(CAMERA.inverse().apply(CAMERA.apply(points)), points, atol=1e-12)
    # a tf2_echo quaternion printed with 4 decimals is normalised, a wrong one refused
    assert np.linalg.norm(RigidTransform.from_parameters([0, 0, 0], [0, 0, 0, 1.0004]).rotation) \
        == pytest.approx(1.0)
    for translation, rotation, reason in (([0, 0], [0, 0, 0, 1], 'translation'),
                                          ([0, 0, 0], [0, 0, 0, 2], 'unit quaternion'),
                                          ([0, 0, 0], [0, 0, 0], 'rotation'),
                                          ([0, 0, float('nan')], [0, 0, 0, 1], 'finite')):
        with pytest.raises(ValueError, match=reason):
            RigidTransform.from_parameters(translation, rotation)


def test_arm_angles_of_a_known_pose():
    joints = np.zeros((len(K4ABT_JOINTS), 3))

    def put(name, xyz):
        joints[JOINT_INDEX[name]] = xyz
    put('pelvis', (0, 0, 0))
    put('spine_chest', (0, 0, 0.5))
    # left: arm straight out sideways (90 deg at the shoulder), elbow bent 90 deg forward,
    # straight wrist
    put('shoulder_left', (0, 0.2, 0.5))
    put('elbow_left', (0, 0.5, 0.5))
    put('wrist_left', (0.3, 0.5, 0.5))
    put('hand_left', (0.4, 0.5, 0.5))
    # right: arm hanging, straight elbow, wrist bent 45 deg
    put('shoulder_right', (0, -0.2, 0.5))
    put('elbow_right', (0, -0.2, 0.2))
    put('wrist_right', (0, -0.2, -0.1))
    put('hand_right', (0.1, -0.2, -0.2))
    np.testing.assert_allclose(arm_angles(joints),
                               [math.pi / 2, 0.0, math.pi / 2, 0.0, 0.0, math.pi / 4],
                               atol=1e-12)
    # angles do not depend on the frame they are computed in
    np.testing.assert_allclose(arm_angles(CAMERA.apply(joints)), arm_angles(joints), atol=1e-12)
    put('hand_right', (0, -0.2, -0.1))          # a hand on its wrist has no direction
    with pytest.raises(ValueError, match='r_wrist'):
        arm_angles(joints)


def test_marker_ids_and_joint_names():
    assert split_marker_id(0) == (0, 0)
    assert split_marker_id(231) == (2, 31)
    assert len(K4ABT_JOINTS) == 32 and K4ABT_JOINTS[JOINT_INDEX['hand_right']] == 'hand_right'
    assert joint_indices(['pelvis', 'nose']).tolist() == [0, 27]
    with pytest.raises(ValueError, match='elbow'):
        joint_indices(['elbow'])


# -- one body ---------------------------------------------------------------------------------
def test_one_body_gives_keypoints_in_the_robot_frame_and_velocities_from_stamps():
    synthetic = SyntheticBody()
    machine = tracker()
    speeds = np.array([0.2, 0.4, 0.6, 0.8, 1.0, 1.2])
    stamps = 100.0 + DT * np.arange(5)
    steps = [machine.frame(frame(t, b1=synthetic.step(speeds, 1, t))) for t in stamps]
    first, *rest = steps
    assert first.followed == 1 and first.velocities is None     # no velocity from one frame
    np.testing.assert_allclose(first.keypoints, body(0.4), atol=1e-9)   # the middle of d = 1
    for step in rest:
        np.testing.assert_allclose(np.abs(step.velocities), speeds, rtol=1e-9)
        np.testing.assert_allclose(step.angles, arm_angles(step.keypoints), atol=1e-12)
    assert first.reports[0].kind == 'follow' and 'following body 1' in first.reports[0].message
    assert all(not step.reports for step in rest)


def test_a_stamp_that_does_not_increase_is_refused():
    machine = tracker()
    machine.frame(frame(1.0, b1=body(1.0)))
    for stamp in (1.0, 0.9):
        with pytest.raises(InputError, match='not after the previous'):
            machine.frame(frame(stamp, b1=body(1.0)))


def test_keypoint_subset_makes_the_skeleton():
    machine = tracker(keypoint_joints=['hand_left', 'hand_right'])
    step = machine.frame(frame(1.0, b1=body(1.0)))
    np.testing.assert_allclose(step.keypoints, body(1.0)[[JOINT_INDEX['hand_left'],
                                                          JOINT_INDEX['hand_right']]], atol=1e-9)


# -- several bodies ---------------------------------------------------------------------------
def test_the_nearest_body_is_followed_and_every_body_gives_the_distance():
    machine = tracker()
    near, far = body(0.5, (1, 0)), body(1.5, (0, 1))
    step = machine.frame(frame(1.0, b3=far, b7=near))
    assert step.followed == 7
    np.testing.assert_allclose(step.keypoints, np.vstack([near, far]), atol=1e-9)  # followed first
    assert step.bodies == pytest.approx({3: 1.5, 7: 0.5})
    np.testing.assert_allclose(step.angles, arm_angles(near), atol=1e-12)


def test_hysteresis_keeps_the_choice_between_two_people_at_about_the_same_distance():
    machine = tracker(switch_margin=0.3)
    followed = []
    t = 1.0
    for i in range(30):
        wobble = 0.1 * (-1) ** i           # they take turns being nearer, by 0.2 m
        t += DT
        followed.append(machine.frame(frame(t, b1=body(1.0 + wobble, (1, 0)),
                                            b2=body(1.0 - wobble, (0, 1)))).followed)
    assert followed == [2] * 30            # the nearest at first, then kept
    # body 1 walks in; the choice switches once it is nearer by more than the margin
    switched = []
    for rho in np.arange(1.12, 0.45, -0.05):     # 0.72, then 0.67: switch
        t += DT
        step = machine.frame(frame(t, b1=body(rho, (1, 0)), b2=body(1.0, (0, 1))))
        switched.append((round(rho, 2), step.followed))
        if step.reports:
            assert 'nearer than body 2 by more than 0.3 m' in step.reports[0].message
    assert [b for rho, b in switched] == [2 if rho >= 0.7 else 1 for rho, _ in switched]
    # and walking back out does not switch back until body 2 is the nearer by the margin
    for rho in np.arange(0.52, 1.15, 0.05):
        t += DT
        assert machine.frame(frame(t, b1=body(rho, (1, 0)), b2=body(1.0, (0, 1)))).followed == 1


def test_a_fixed_body_id_is_followed_and_missing_it_gives_no_joint_states():
    machine = tracker(follow_body=4)
    step = machine.frame(frame(1.0, b1=body(0.5, (1, 0)), b4=body(1.5, (0, 1))))
    assert step.followed == 4
    step = machine.frame(frame(1.0 + DT, b1=body(0.5, (1, 0))))
    assert step.followed is None and step.angles is None and step.velocities is None
    assert step.reports[0].level == 'WARN' and 'not in view' in step.reports[0].message
    np.testing.assert_allclose(step.keypoints, body(0.5, (1, 0)), atol=1e-9)  # distance counts


# -- bad streams ------------------------------------------------------------------------------
def test_no_body_in_view_is_a_missing_input_and_a_returning_body_starts_again():
    machine = tracker()
    speeds = np.full(6, 0.5)
    synthetic = SyntheticBody()
    t = 1.0
    machine.frame(frame(t, b1=synthetic.step(speeds, 2, t)))
    with pytest.raises(InputError, match='no body in view.*left'):
        machine.frame(BodyFrame(None, {}))
    with pytest.raises(InputError, match='no body in view'):
        machine.frame(BodyFrame(None, {}))
    assert machine.followed is None
    t += 5 * DT                        # the same person, back, where it was
    step = machine.frame(frame(t, b1=synthetic.step(speeds, 2, t)))
    assert step.followed == 1 and step.velocities is None   # velocities start again
    t += DT
    step = machine.frame(frame(t, b1=synthetic.step(speeds, 2, t)))
    np.testing.assert_allclose(np.abs(step.velocities), speeds, rtol=1e-9)


def test_two_bodies_swapping_ids_keep_the_followed_person():
    machine = tracker(switch_margin=0.3)
    a, b = body(0.8, (1, 0)), body(1.0, (0, 1))
    assert machine.frame(frame(1.0, b1=a, b2=b)).followed == 1
    step = machine.frame(frame(1.0 + DT, b1=b, b2=a))      # the tracker swapped their ids
    assert step.followed == 2 and step.velocities is None  # the same person, velocities restart
    np.testing.assert_allclose(step.keypoints[:len(a)], a, atol=1e-9)
    assert 'under a new id' in step.reports[0].message
    step = machine.frame(frame(1.0 + 2 * DT, b1=b, b2=a))
    assert step.followed == 2 and step.velocities is not None


def test_a_jump_of_metres_is_dropped_until_it_holds():
    machine = tracker(confirm_frames=3)
    machine.frame(frame(1.0, b1=body(0.5)))
    gate = 3.0 * DT + JUMP_SLACK
    for i in range(1, 3):            # 2 m in one frame: dropped, twice
        with pytest.raises(InputError, match='tracking jump'):
            machine.frame(frame(1.0 + i * DT, b1=body(2.5)))
    step = machine.frame(frame(1.0 + 3 * DT, b1=body(2.5)))   # the third frame: it is there
    assert step.followed == 1 and step.velocities is None
    assert step.reports[0].kind == 'relocated'
    np.testing.assert_allclose(step.keypoints, body(2.5), atol=1e-9)
    # a move inside the gate is a move, not a jump
    assert machine.frame(frame(1.0 + 4 * DT, b1=body(2.5 - 0.9 * gate))).followed == 1


def test_a_jump_toward_the_robot_keeps_its_skeleton_while_it_is_confirmed():
    """A jump in the unsafe direction (2 m -> 0.3 m in one frame) was dropped like any jump,
    so the estimator's window kept the older, farther skeleton: d 3 while the person stood in
    the inner circle. Its skeleton now goes out at once; only its joint states wait."""
    machine = tracker(confirm_frames=3)
    for i in range(5):
        machine.frame(frame(1.0 + i * DT, b1=body(2.0)))
    for i in range(5, 7):
        step = machine.frame(frame(1.0 + i * DT, b1=body(0.3)))
        assert distance_level(step.keypoints) == 1 and step.velocities is None
        assert step.followed is None and [r.kind for r in step.reports] == ['jump_nearer']
        assert 'tracking jump' in step.reports[0].message
    step = machine.frame(frame(1.0 + 7 * DT, b1=body(0.3)))        # confirmed: followed again
    assert step.followed == 1 and step.reports[0].kind == 'relocated'
    # the safe direction is still dropped: the nearer skeleton stays the latest
    with pytest.raises(InputError, match='tracking jump'):
        machine.frame(frame(1.0 + 8 * DT, b1=body(2.5)))


def test_stamps_that_go_back_more_than_max_gap_start_the_tracker_again():
    """A restarted driver, a stepped clock or a looped bag: every frame was dropped until the
    stamps passed the old ones (hours, maybe). Beyond max_gap back, it starts again."""
    machine = tracker(max_gap=0.5, confirm_frames=3)
    for i in range(5):
        machine.frame(frame(1000.0 + i * DT, b1=body(1.0)))
    with pytest.raises(InputError, match='not after the previous'):
        machine.frame(frame(1000.0, b1=body(1.0)))              # a small reversal: dropped
    for i in range(2):                                          # far back: confirmed first
        with pytest.raises(InputError, match='once it holds for 3 frames'):
            machine.frame(frame(10.0 + i * DT, b1=body(1.0)))
    step = machine.frame(frame(10.0 + 2 * DT, b1=body(1.0)))
    assert [r.kind for r in step.reports][:1] == ['stamp_back'] and step.velocities is None
    assert step.followed == 1
    assert machine.frame(frame(10.0 + 3 * DT, b1=body(1.0))).velocities is not None


def test_a_second_stream_with_an_older_clock_never_passes_between_the_live_frames():
    """A bag played on a live cell: its frames (a person 2.5 m away, stamps ~990 s back)
    interleave with the live ones (a person at 0.3 m). Restarting on any frame far back let
    every recorded frame through, and the distance read d 3 every other frame."""
    machine = tracker(max_gap=0.5, confirm_frames=3)
    for i in range(60):
        live = 1000.0 + i * DT
        step = machine.frame(frame(live, b1=body(0.3)))
        assert distance_level(step.keypoints) == 1
        with pytest.raises(InputError, match='not after the previous'):
            machine.frame(frame(10.0 + i * DT, b1=body(2.5)))


# -- a second stream (issue 17) -------------------------------------------------------------
AHEAD = 2.0                      # seconds: the second stream's stamps, more than max_gap ahead


def two_streams(machine, second_bodies, frames=30, live_first=True):
    """A live stream (sequence 5000.., a person at 0.1 m) and a second one (sequence 1..,
    stamped AHEAD s ahead, `second_bodies`) interleaved, as the node gets them; the steps of
    both, in order, as (stream, step or the InputError)."""
    out = []
    for i in range(frames):
        live = (frame(100.0 + i * DT, b1=body(0.1)), Stamp(0, 5000 + i))
        second = (frame(100.0 + AHEAD + i * DT, **second_bodies), Stamp(0, 1 + i))
        for name, (f, source) in (('live', live), ('second', second)) if live_first \
                else (('second', second), ('live', live)):
            try:
                out.append((name, machine.frame(f, source, now=10.0 + i * DT)))
            except InputError as exc:
                out.append((name, exc))
    return out


@pytest.mark.parametrize('second_bodies', [
    {'b1': body(3.0)},                                         # the same body id, far away
    {'b1': body(3.0), 'b2': body(2.5, (0, 1))},                # two body ids
], ids=['same-id', 'two-ids'])
def test_a_second_stream_stamped_ahead_never_takes_over(second_bodies):
    """Issue 17: a second body_tracking_data stream stamped more than max_gap ahead made the
    live frames 'not after the previous one': with the person at 0.1 m the estimator read
    d = 3 from the second stream. The adapter follows one publisher: the live one."""
    machine = tracker(max_gap=0.5)
    steps = two_streams(machine, second_bodies)
    live = [s for name, s in steps if name == 'live']
    assert all(isinstance(s, type(live[0])) and not isinstance(s, InputError) for s in live)
    assert all(distance_level(s.keypoints) == 0 for s in live)
    assert all(s.followed == 1 for s in live) and all(s.velocities is not None
                                                    for s in live[1:])
    second = [s for name, s in steps if name == 'second']
    assert all(isinstance(s, InputError) and 'second body-tracking stream' in str(s)
               for s in second)
    assert machine.lock.others == len(second)


def test_when_two_streams_disagree_the_nearer_wins():
    """The stream followed first is the far one (a bag of someone 3 m away); a second
    tracker sees the person at 0.1 m: its skeleton is published, and every skeleton of the
    followed stream carries it while it is recent (max_gap)."""
    machine = tracker(max_gap=0.5)
    steps = two_streams(machine, {'b1': body(3.0)}, live_first=False)
    assert distance_level(steps[0][1].keypoints) == 3          # nobody nearer seen yet
    followed = [s for name, s in steps[1:] if name == 'second']
    assert all(distance_level(s.keypoints) == 0 for s in followed)   # the far stream's too
    nearer = [s for name, s in steps if name == 'live' and not isinstance(s, InputError)]
    assert nearer and all(s.velocities is None and s.reports[0].kind == 'nearer_reading'
                          and distance_level(s.keypoints) == 0 for s in nearer)
    # the near stream stops: after max_gap the followed stream's far person is the distance
    later = machine.frame(frame(200.0, b1=body(3.0)), Stamp(0, 31), now=20.0)
    assert distance_level(later.keypoints) == 3


def test_without_sequence_numbers_the_nearer_rule_still_holds():
    """An rmw without sequence numbers: both streams look like one, the ahead one is taken
    and the live frames go 'back'; they are not taken, but the nearer person is published."""
    machine = tracker(max_gap=0.5)
    published = []
    for i in range(30):
        ahead = machine.frame(frame(100.0 + AHEAD + i * DT, b1=body(3.0)), now=10.0 + i * DT)
        published.append(ahead)
        try:
            published.append(machine.frame(frame(100.0 + i * DT, b1=body(0.1)),
                                           now=10.0 + i * DT))
        except InputError as exc:
            assert 'not after the previous' in str(exc)
    assert distance_level(published[0].keypoints) == 3 and len(published) > 30
    assert all(distance_level(s.keypoints) == 0 for s in published[1:])   # never d = 3 again


def test_a_camera_pose_or_joints_beyond_the_cell_are_refused():
    with pytest.raises(ValueError, match='metres expected'):
        RigidTransform.from_parameters([1e308, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])
    machine = tracker()
    far = body(1.0) + [25.0, 0.0, 0.0]                       # 26 m: no tracker of the cell
    with pytest.raises(InputError, match='farther than'):
        machine.frame(frame(1.0, b1=far))


def test_a_jump_that_does_not_hold_is_dropped_and_the_body_keeps_its_place():
    machine = tracker(confirm_frames=3)
    machine.frame(frame(1.0, b1=body(0.5)))
    with pytest.raises(InputError, match='tracking jump'):
        machine.frame(frame(1.0 + DT, b1=body(2.5)))
    with pytest.raises(InputError, match='tracking jump'):
        machine.frame(frame(1.0 + 2 * DT, b1=body(4.5)))   # jumping around: never confirmed
    step = machine.frame(frame(1.0 + 3 * DT, b1=body(0.52)))
    assert step.followed == 1 and not step.reports


def test_a_gap_restarts_the_velocities():
    machine = tracker(max_gap=0.5)
    machine.frame(frame(1.0, b1=body(0.5)))
    step = machine.frame(frame(1.6, b1=body(0.5)))
    assert step.followed == 1 and step.velocities is None
    assert machine.frame(frame(1.6 + DT, b1=body(0.5))).velocities is not None


def test_no_frame_ever_gives_a_wrong_distance_level():
    """A random stream of good and bad frames (people walking, entering, leaving, swapping ids,
    jumping): every frame that gives an input gives the distance level of everyone in it, and
    joint states only with that skeleton."""
    rng = np.random.default_rng(7)
    machine = tracker()
    position = {1: 1.0, 2: 2.0}
    directions = {1: (1, 0), 2: (0, 1)}
    t, given, refused = 100.0, 0, 0
    for _ in range(600):
        t += DT
        for b in position:
            position[b] = float(np.clip(position[b] + rng.uniform(-0.08, 0.08), 0.05, 3.0))
        people = {b: body(position[b], directions[b]) for b in position
                  if rng.random() > 0.1}
        event = rng.random()
        if event < 0.05 and len(people) == 2:
            people = {1: people[2], 2: people[1]}              # swapped ids
        elif event < 0.1 and people:
            b = next(iter(people))
            people[b] = people[b] + [rng.uniform(1.5, 3.0), 0.0, 0.0]  # a jump of metres
        bodies = {b: CAMERA.inverse().apply(j) for b, j in people.items()}
        try:
            step = machine.frame(BodyFrame(t if bodies else None, bodies))
        except InputError:
            refused += 1
            continue
        given += 1
        everyone = np.vstack(list(people.values()))
        assert distance_level(step.keypoints) == distance_level(everyone)
        assert closest_distance(step.keypoints, (0, 0, 0)) == \
            pytest.approx(closest_distance(everyone, (0, 0, 0)))
        if step.velocities is not None:
            assert step.followed in people
    assert given > 300 and refused > 20


# -- the synthetic tracker --------------------------------------------------------------------
def test_synthetic_angles_stay_in_range_after_a_long_gap():
    """A turn longer than the angle range (1.5 rad/s over a 2 s sensor dropout) once left the
    range, below 0 where the measured angle folds; the angles now fold back inside, and the
    next steps turn at the given speeds again."""
    synthetic = SyntheticBody()
    speeds = np.full(6, 1.5)
    synthetic.step(speeds, 2, 0.0)
    for t in (2.0, 4.3, 7.1):                                     # gaps of 2-3 s
        angles = arm_angles(synthetic.step(speeds, 2, t))
        assert np.all((angles >= ANGLE_RANGE[0]) & (angles <= ANGLE_RANGE[1])), angles
        np.testing.assert_allclose(synthetic.angles, angles, atol=1e-9)
    previous = arm_angles(synthetic.step(speeds, 2, 8.0))
    after = arm_angles(synthetic.step(speeds, 2, 8.0 + DT))
    np.testing.assert_allclose(np.abs(after - previous) / DT, speeds, rtol=1e-8)


@pytest.mark.parametrize('direction', [(1.0, 0.0), (-0.3, 1.0)])
def test_synthetic_body_turns_at_the_given_speeds_and_walks_into_the_level_band(direction):
    rng = np.random.default_rng(3)
    synthetic = SyntheticBody(direction=list(direction) + [0.0])
    segments = [1, 3, 0, 2, 3, 1]
    t, previous, previous_rho = 0.0, None, None
    for level in segments:
        seen = []
        for _ in range(15):               # half a second at 30 Hz
            t += DT
            speeds = rng.uniform(0.0, 2.4, size=6)
            joints = synthetic.step(speeds, level, t)
            angles = arm_angles(joints)
            assert np.all((angles >= ANGLE_RANGE[0]) & (angles <= ANGLE_RANGE[1]))
            if previous is not None:
                np.testing.assert_allclose(np.abs(angles - previous) / DT, speeds, rtol=1e-8,
                                           atol=1e-9)
                assert abs(synthetic.rho - previous_rho) <= 3.0 * DT + 1e-12   # it walks
            previous, previous_rho = angles, synthetic.rho
            assert closest_distance(joints, (0, 0, 0)) == pytest.approx(synthetic.rho)
            seen.append(distance_level(joints))
        # inside the band within 0.4 s (12 frames), and then it stays there
        arrival = seen.index(level)
        assert arrival < 12 and set(seen[arrival:]) == {level}, (level, seen)
        lo, hi = distance_band(level, DEFAULT_SAFETY_RADII)
        assert lo <= synthetic.rho <= hi
