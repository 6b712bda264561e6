"""The bridge's monitor (core/robot/guard.py): SSM checked on what is measured, whoever sent the
goal, and the inputs that can only stop the arm.

A bridge and a simulated controller (`TrajectoryFollower`) are stepped together at 100 Hz, as
test_robot.py's Rig does; the attacks reach the controller or the bridge as a hostile or broken
world would send them: a goal the bridge did not send, joint states whose velocities lie, a
tracker that freezes or jumps away, a second writer of hrc/action and hrc/task_state.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from hrc_ros.core.cell.person import SimulatedPerson
from hrc_ros.core.config import load_config
from hrc_ros.core.mdp.policy import default_policy_path, load_policy
from hrc_ros.core.model import HRCModel
from hrc_ros.core.paths import arm_config_path
from hrc_ros.core.cell.tracking import K4ABT_JOINTS
from hrc_ros.core.protocol import InputError
from hrc_ros.core.robot.arm import (JOINT_NAMES, Arm, BodyCapsules, Trajectory,
                                    TrajectoryFollower, body_capsules, peak_link_speed)
from hrc_ros.core.robot.cell import ArmCell, person_seed
from hrc_ros.core.robot.bridge import WRITER_HOLD, Bridge, load_programs, load_robot_description
from hrc_ros.core.robot.guard import (MeasuredSpeed, SkeletonCheck, SpeedEnvelope,
                                      path_deviation)
from hrc_ros.core.study.evaluation import episodes_of

MS = 1_000_000
NOISE = np.random.default_rng(33)


@pytest.fixture(scope='module')
def setup():
    description = load_robot_description()
    return description, load_programs(description), Arm()


def person(distance: float, theta: float = math.radians(-31)) -> np.ndarray:
    """The 32 keypoints of a person standing `distance` m from the base, hands down."""
    p = SimulatedPerson(3, seed=0)
    p.rho, p.theta, p.reach = distance, theta, 0.0
    return p.keypoints()


def seen(keypoints, noise=0.0015) -> BodyCapsules:
    """What a real tracker reports: millimetres of noise on every keypoint."""
    return body_capsules(keypoints + NOISE.normal(0.0, noise, keypoints.shape), K4ABT_JOINTS)


class Cell:
    """A bridge and a controller at 100 Hz; `foreign(trajectory)` is a goal someone else sends
    the controller, `lie` replaces the velocities the controller reports, `frozen` (positions,
    velocities) the whole state the driver reports."""

    def __init__(self, setup, distance=2.5):
        self.description, programs, self.arm = setup
        self.bridge = Bridge(self.description, programs, self.arm, period=0.01)
        self.follower = TrajectoryFollower(self.description.poses['home'],
                                           self.description.ssm.deceleration)
        self.keypoints = person(distance)
        self.t = 0
        self.lie = None
        self.frozen = None
        self.commands = []

    def foreign(self, target, duration):
        q = self.follower.q
        traj = Trajectory(JOINT_NAMES, np.array([q, target]), np.array([duration]),
                          peak_link_speed(self.arm, q, target, duration), (-1,), 'forged')
        self.follower.follow(traj)

    def run(self, seconds, override=None, body=None):
        out = []
        for _ in range(int(round(seconds / 0.01))):
            self.bridge.skeleton(seen(self.keypoints) if body is None else body(), self.t,
                                 self.t)
            qd = self.follower.qd if self.lie is None else self.lie
            q, qd = (self.follower.q, qd) if self.frozen is None else self.frozen
            self.bridge.joint_state(JOINT_NAMES, q, qd, self.t, self.t)
            command = self.bridge.tick(self.t)
            if command.trajectory is not None:
                self.follower.follow(command.trajectory)
            self.follower.step(0.01, command.override if override is None else override)
            out.append((command, self.follower.q.copy(), self.follower.qd.copy()))
            self.t += 10 * MS
        self.commands += out
        return out


def program_running(cell):
    cell.run(0.3)                                       # SSM's start-up stop clears
    cell.bridge.task_state(dict(tp=1, tc=3, tx=0, ty=0, hp=0, hc=0, bp=0, bc=0), cell.t)
    cell.bridge.action('ct', cell.t)
    cell.run(0.6)
    assert cell.bridge.motion == 'program' and np.max(np.abs(cell.follower.qd)) > 0.1


# -- the parts -------------------------------------------------------------------------------
def test_the_measured_speed_takes_the_positions_when_the_velocities_lie(setup):
    _, _, arm = setup
    q0 = np.array([1.4, -1.9, 1.9, -1.57, -1.57, 0.0])
    qd = np.array([0.0, 0.5, 0.0, 0.0, 0.0, 0.0])
    measured = MeasuredSpeed(arm)
    measured.update(q0, np.zeros(6), 0)
    # within min_dt (30 ms) of the last sample: no difference yet (the stamps' jitter over one
    # 8 ms period would read as motion), the reported velocities alone
    assert measured.update(q0 + qd * 0.008, np.zeros(6), 8 * MS) == 0.0
    speed = measured.update(q0 + qd * 0.032, np.zeros(6), 32 * MS)    # zeros reported
    assert measured.reported == 0.0
    assert speed == pytest.approx(arm.link_speed(q0 + qd * 0.032, qd), rel=1e-9)
    # the reported velocities win when they are the larger (a position that did not move yet)
    assert measured.update(q0 + qd * 0.032, 2 * qd, 40 * MS) == pytest.approx(
        arm.link_speed(q0 + qd * 0.032, 2 * qd))
    # a sample older than the one before restarts the differences (no division by <= 0)
    assert measured.update(q0, np.zeros(6), 4 * MS) == 0.0
    # stamps jittered by 0.5 ms at 125 Hz on an arm at a steady 0.5 rad/s: no false motion
    jitter = np.random.default_rng(4)
    quiet = MeasuredSpeed(arm)
    true = arm.link_speed(q0, qd)
    for k in range(1, 200):
        t = k * 0.008
        quiet.update(q0 + qd * t, qd, int((t + jitter.uniform(-5e-4, 5e-4)) * 1e9))
        assert quiet.speed <= true * 1.05 + 0.02


def test_the_envelope_holds_each_command_for_the_latency_then_falls_at_the_deceleration():
    envelope = SpeedEnvelope(deceleration=2.0, latency=0.04)
    envelope.command(0, 1.0)
    envelope.command(10 * MS, 0.0)
    assert envelope.limit(30 * MS) == pytest.approx(1.0)            # still in the latency
    assert envelope.limit(140 * MS) == pytest.approx(1.0 - 2.0 * 0.1)
    assert envelope.limit(600 * MS) == 0.0
    envelope.command(600 * MS, 0.3)
    assert envelope.limit(600 * MS) == pytest.approx(0.3)


def test_the_envelope_over_a_span_is_the_most_it_allowed_at_any_instant_of_it():
    """A difference of positions is the mean speed over its span: what the commands allowed
    anywhere in the span bounds it, each command from when it was given."""
    envelope = SpeedEnvelope(deceleration=2.0, latency=0.02, horizon=0.1)
    envelope.command(0, 0.5)
    envelope.command(20 * MS, 0.1)
    envelope.command(40 * MS, 0.0)
    assert envelope.limit(60 * MS) == pytest.approx(0.5 - 2.0 * 0.04)
    assert envelope.limit(60 * MS, 20 * MS) == pytest.approx(0.5)       # in its latency then
    assert envelope.limit(100 * MS, 50 * MS) == pytest.approx(0.5 - 2.0 * 0.03)
    envelope.command(100 * MS, 0.3)                   # counts from when it was given, whole
    assert envelope.limit(100 * MS, 50 * MS) == pytest.approx(0.3 + 0.14)
    # a command decayed to nothing stays for the horizon: a span reaching back still sees it
    envelope.command(280 * MS, 0.0)
    assert envelope.limit(300 * MS) == 0.0
    assert envelope.limit(300 * MS, 250 * MS) == pytest.approx(0.3 - 2.0 * 0.13)
    assert envelope.limit(500 * MS) == 0.0
    assert envelope.limit(500 * MS, 250 * MS) == 0.0     # gone once decayed a horizon ago


def test_the_path_deviation_is_the_distance_to_the_waypoints_polyline():
    points = np.array([[0.0] * 6, [1.0] + [0.0] * 5, [1.0, 1.0] + [0.0] * 4])
    assert path_deviation([0.5, 0, 0, 0, 0, 0], points) == pytest.approx(0.0)
    assert path_deviation([1.0, 0.5, 0, 0, 0, 0], points) == pytest.approx(0.0)
    assert path_deviation([0.5, 0, 0.2, 0, 0, 0], points) == pytest.approx(0.2)
    assert path_deviation([0.0, 0, 0, 0, 0, 0.3], points[:1]) == pytest.approx(0.3)


def test_a_skeleton_is_frozen_within_the_tolerance_and_a_jump_away_is_too_fast():
    check = SkeletonCheck(frozen_tolerance=0.0005, max_body_speed=3.0)
    body = body_capsules(person(2.0), K4ABT_JOINTS)
    assert check.unchanged(body, body)
    assert check.unchanged(BodyCapsules(body.segments + 0.0004, body.radii, body.names), body)
    assert not check.unchanged(seen(person(2.0)), body)
    assert not check.jumped_away(1.0 + 0.079, 1.0, 0.01)     # within 3 m/s x 10 ms + 0.05 m
    assert check.jumped_away(1.0 + 0.081, 1.0, 0.01)
    assert not check.jumped_away(0.2, 1.0, 0.01)                      # toward the arm: taken


# -- a goal the bridge did not send ----------------------------------------------------------
def test_a_goal_the_bridge_did_not_send_cannot_run_on_an_idle_arms_override(setup):
    """The bridge has nothing of its own to move: its override is 0, so a forged goal does not
    move the arm at all (before: 1.0, and the goal ran at full speed)."""
    cell = Cell(setup)
    cell.run(0.3)
    cell.bridge.action('nw', cell.t)
    start = cell.follower.q.copy()
    cell.foreign(cell.description.poses['retreat'], 1.5)
    steps = cell.run(1.0)
    assert all(c.override == 0.0 for c, _, _ in steps)
    np.testing.assert_array_equal(cell.follower.q, start)


def test_a_goal_the_bridge_did_not_send_stops_the_arm_and_is_replaced(setup):
    """A forged goal replaces the running program in the controller (a new message replaces
    the running trajectory): the monitor stops the arm, and at rest the bridge's own goal
    replaces the forged one, from where the arm stands; the program then goes on."""
    cell = Cell(setup)
    program_running(cell)
    start = cell.follower.q.copy()
    cell.foreign(cell.description.poses['retreat'], 1.2)
    steps = cell.run(1.5)
    stops = [i for i, (c, _, _) in enumerate(steps) if c.stop]
    assert stops and ('did not send' in steps[stops[0]][0].reason)
    assert all(c.override == 0.0 for c, _, _ in steps[stops[0]:stops[0] + 20])
    # it brakes at the SSM deceleration from where it was caught, and stands; there the
    # bridge's own goal (the program, from where the arm stands) replaces the forged one
    sent = next(i for i, (c, _, _) in enumerate(steps) if c.trajectory is not None)
    assert sent > stops[0] and steps[sent][0].trajectory.kind == 'program'
    np.testing.assert_allclose(steps[sent][0].trajectory.positions[0], steps[sent - 1][1],
                               atol=1e-9)
    travelled = max(np.max(np.abs(q - start)) for _, q, _ in steps[:sent])
    assert travelled < 0.05
    assert cell.bridge.counts['foreign_motion'] == 1
    done = cell.bridge.progress.cycles_done
    cell.run(4.0)
    assert not cell.commands[-1][0].stop and cell.bridge.progress.cycles_done > done


def test_the_honest_batch_cell_has_no_monitor_stops():
    """SSM brakes the arm as a person comes near; its positions' difference is the mean speed
    over its span (40 ms: the batch cell's joint states come every 20 ms, and a span is at least
    30 ms), higher than it may move now. Before the envelope took spans, the
    monitor read that as motion the bridge did not send: 7 stops in these two episodes of the
    honest batch cell under SSM alone (1.4 an episode over 60), each dropping the running
    goal."""
    config = load_config(arm_config_path())
    model = HRCModel(config)
    scenarios, seeds = episodes_of(model, 'random', 2, 50, 0, 0.5)
    cell = ArmCell(model, load_policy(default_policy_path(config), config))
    for e, (scenario, human) in enumerate(zip(scenarios, seeds)):
        out = cell.episode(scenario, human, person_seed(0, e), 'ssm_only', record=True)
        assert sum(stop for _, stop, _, _ in out.samples) > 0       # SSM stopped the arm
        assert out.monitor['foreign_motion'] == 0 and out.monitor['overspeed'] == 0, e
        assert out.monitor['frozen_joint_states'] == 0, e


def test_a_slower_goal_off_the_bridges_path_stops_the_program(setup):
    cell = Cell(setup)
    program_running(cell)
    cell.run(0.5, override=0.0)                   # the program brakes to rest ...
    q = cell.follower.q.copy()
    target = q + np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.6])    # ... a slow wrist turn elsewhere
    cell.foreign(target, 3.0)
    steps = cell.run(1.0)
    reasons = [c.reason for c, _, _ in steps if c.stop]
    assert any("off the bridge's path" in r or 'did not send' in r for r in reasons)
    assert np.max(np.abs(cell.follower.q - q)) <= cell.description.path_tolerance + 0.02


def test_velocities_that_lie_do_not_hide_a_forged_motion(setup):
    """A driver that reports zero velocities: the positions' differences show the motion."""
    cell = Cell(setup)
    program_running(cell)
    cell.lie = np.zeros(6)
    start = cell.follower.q.copy()
    path = cell.bridge.active.positions
    cell.foreign(cell.description.poses['retreat'], 1.2)
    steps = cell.run(2.0)
    first = next(i for i, (c, _, _) in enumerate(steps) if c.stop)
    assert 'did not send' in steps[first][0].reason
    # off the bridge's path by path_tolerance (one control period's motion on top) ...
    assert path_deviation(steps[first][1], path) < cell.description.path_tolerance + 0.01
    # ... and held stopped until the bridge's own goal replaced the forged one at rest
    sent = next(i for i, (c, _, _) in enumerate(steps) if c.trajectory is not None)
    assert all(c.stop for c, _, _ in steps[first:sent + 1])
    assert np.max(np.abs(steps[sent - 1][1] - start)) < 0.5


def test_measured_speed_above_what_ssm_allows_is_a_protective_stop(setup):
    """The person comes near while the arm runs at full speed on a goal whose nominal speed
    understates it (a controller that runs faster than the timing it was given): SSM's
    override alone would let it go on; the measured speed stops it."""
    cell = Cell(setup)
    program_running(cell)
    active = cell.bridge.active
    cell.bridge.active = Trajectory(active.joint_names, active.positions, active.durations,
                                    active.nominal_speed / 4, active.marks, active.kind)
    cell.keypoints = person(1.45)
    steps = cell.run(0.4)
    reasons = [c.reason for c, _, _ in steps if c.stop]
    assert any('SSM allows' in r or 'did not send' in r for r in reasons), reasons[:3]


# -- a broken or hostile tracker -------------------------------------------------------------
def test_a_frozen_tracker_stops_the_arm_with_its_reason_and_a_live_one_does_not(setup):
    cell = Cell(setup)
    program_running(cell)
    frozen = seen(cell.keypoints)
    steps = cell.run(1.0, body=lambda: frozen)            # fresh stamps, the same keypoints
    reasons = [c.reason for c, _, _ in steps if c.stop]
    assert reasons and 'frozen tracker' in reasons[-1]
    stopped_at = next(i for i, (c, _, _) in enumerate(steps) if c.stop)
    # the data ages from the last change: SSM slows the arm and stops it at human_timeout
    assert stopped_at * 0.01 <= cell.description.ssm.human_timeout + 0.02
    assert np.all(steps[-1][2] == 0)
    # a live tracker again: the arm resumes
    steps = cell.run(1.0)
    assert not steps[-1][0].stop


def test_a_clock_that_steps_back_drops_what_is_held_and_holds_the_arm(setup):
    """The bridge's clock steps back 30 s (an NTP step, a /clock that restarted) and the
    tracker stops at that moment: the skeleton held, stamped in the clock's future, read as 0 s
    old, and SSM let the program run on with nobody seen for the length of the step (a review
    found override 0.97 at 45 s). Now the next tick sees the step, drops what is held and holds
    the arm while nobody is seen; the arm brakes within what was commanded (no monitor fault)
    and the program resumes once the tracker sends again."""
    cell = Cell(setup)
    program_running(cell)
    cell.t -= 30_000 * MS
    steps = []
    for _ in range(150):        # 1.5 s: the joint states go on, the tracker is silent
        cell.bridge.joint_state(JOINT_NAMES, cell.follower.q, cell.follower.qd, cell.t, cell.t)
        command = cell.bridge.tick(cell.t)
        cell.follower.step(0.01, command.override)
        steps.append(command)
        cell.t += 10 * MS
    assert steps[0].stop
    assert 'the clock stepped back: data held is stamped 29.99' in steps[0].reason
    assert all(c.stop and c.override == 0.0 for c in steps), [c.reason for c in steps[-3:]]
    assert 'no human data' in steps[-1].reason and not cell.bridge.fault
    assert np.all(cell.follower.qd == 0) and cell.bridge.counts['clock_steps'] == 1
    steps = cell.run(1.5)                                 # the tracker again
    assert not steps[-1][0].stop and np.max(np.abs(steps[-1][2])) > 0.1
    assert cell.bridge.counts['clock_steps'] == 1 and cell.bridge.motion == 'program'


def test_joint_states_frozen_while_the_arm_moves_stop_it_and_a_slow_honest_arm_does_not(setup):
    """The driver repeats its last state (the positions and velocities of an arm moving at
    speed) with fresh stamps while the controller goes on: the bridge saw fresh joint states
    and let the program run on stale positions until the stall rule held it about 4 s later.
    Now positions that moved less than a quarter of what the velocities say over
    joint_state_timeout are no data: a protective stop, the real arm brakes, and the program
    goes on once the driver reports motion again. An arm moving just above rest_speed is no
    freeze."""
    cell = Cell(setup)
    program_running(cell)
    cell.frozen = (cell.follower.q.copy(), cell.follower.qd.copy())
    steps = cell.run(1.0)
    stopped = [i for i, (c, _, _) in enumerate(steps) if c.stop]
    timeout = cell.description.joint_state_timeout
    assert stopped and stopped[0] * 0.01 <= timeout + 0.02, stopped[:3]
    assert all(c.stop and c.override == 0.0 for c, _, _ in steps[stopped[0]:])
    assert 'a frozen driver' in steps[-1][0].reason and not cell.bridge.fault
    assert np.all(steps[-1][2] == 0)                    # the arm itself braked and stands
    assert cell.bridge.counts['frozen_joint_states'] == 1
    cell.frozen = None                                  # the driver again
    steps = cell.run(1.5)
    assert not steps[-1][0].stop and np.max(np.abs(steps[-1][2])) > 0.1
    assert cell.bridge.counts['frozen_joint_states'] == 1
    # an arm crawling at 1.5 rest_speed on one joint reports that motion: no freeze
    crawl = np.zeros(6)
    crawl[0] = 1.5 * cell.description.rest_speed
    q = cell.follower.q.copy()
    for k in range(50):
        cell.bridge.joint_state(JOINT_NAMES, q + crawl * k * 0.01, crawl, cell.t, cell.t)
        assert 'frozen driver' not in cell.bridge.tick(cell.t).reason
        cell.t += 10 * MS


@pytest.mark.parametrize('disguise', ['jitter', 'two_states', 'rest_blips', 'rest_runs'])
def test_a_frozen_driver_that_jitters_flips_or_blips_rest_is_still_frozen(setup, disguise):
    """An adversarial review of the first rule (positions within 1e-4 rad for 0.1 s): 2e-4
    rad of jitter on the frozen positions, or a flip between two states 1.5e-4 rad apart, or
    every 9th message at rest, restarted its clock at every message, escaped the stall rule
    too (its velocities never read as rest), and ran the arm 0.17 m/s faster than SSM allowed
    a person 1.2 m away. Such motion adds nothing along what the velocities claim. A second
    review: three messages at rest in every four cleared the stop whenever the last three were
    at rest (153 of 600 ticks free): a stop now holds until the checks agree for
    joint_state_timeout."""
    cell = Cell(setup)
    program_running(cell)
    q, qd = cell.follower.q.copy(), cell.follower.qd.copy()
    rng = np.random.default_rng(5)
    messages = []
    for k in range(30):
        if disguise == 'jitter':
            messages.append((q + rng.uniform(-2e-4, 2e-4, 6), qd))
        elif disguise == 'two_states':
            messages.append((q + 1.5e-4 * (k % 2), qd))
        elif disguise == 'rest_blips':
            messages.append((q, np.zeros(6) if k % 9 == 0 else qd))
        else:
            messages.append((q, qd if k % 4 == 0 else np.zeros(6)))
    messages *= 3
    steps = []
    for frozen in messages:
        cell.frozen = frozen
        steps += cell.run(0.01)
    stopped = [i for i, (c, _, _) in enumerate(steps) if c.stop]
    assert stopped and stopped[0] * 0.01 <= cell.description.joint_state_timeout + 0.02, \
        [c.reason for c, _, _ in steps[:12]]
    assert all(c.stop and c.override == 0.0 for c, _, _ in steps[stopped[0]:]), \
        [i for i, (c, _, _) in enumerate(steps) if not c.stop]
    assert 'a frozen driver' in steps[-1][0].reason
    assert cell.bridge.counts['frozen_joint_states'] == 1


def test_positions_that_fall_ever_further_behind_stop_the_arm(setup):
    """A driver whose positions lag ever further behind (a backlog, a replay at half the real
    rate) with fresh stamps: over 0.1 s they move half of what their velocities claim, more
    than the quarter the short check asks, and nothing else saw it (an adversarial review: the
    arm ran 2.3 s with the reported positions up to 0.38 rad behind). Over LAG_WINDOW they
    fall behind the claim: a stop within it (1 s)."""
    cell = Cell(setup)
    program_running(cell)
    history = []                                # what the arm did: (t, q, qd)
    start = cell.t
    steps = []
    for _ in range(200):
        history.append((cell.t, cell.follower.q.copy(), cell.follower.qd.copy()))
        past = start + (cell.t - start) // 2    # the arm's state at half the real rate
        _, q, qd = next(h for h in reversed(history) if h[0] <= past)
        cell.frozen = (q, qd)
        steps += cell.run(0.01)
    stopped = [i for i, (c, _, _) in enumerate(steps) if c.stop]
    assert stopped and stopped[0] * 0.01 <= 1.05, [c.reason for c, _, _ in steps[:3]]
    assert 'a frozen driver' in steps[stopped[0]][0].reason


def test_the_override_needs_a_consumer_not_only_a_reader():
    """Only a node that acts on the override lets the arm move: a display (the HMI), a
    recorder or an echo reads it and cannot stop the arm."""
    from hrc_ros.core.robot.bridge import OVERRIDE_CONSUMERS, unconsumed_reason
    topic = '/hrc/speed_override'
    assert unconsumed_reason(topic, ['hmi', 'cobot_sim'], OVERRIDE_CONSUMERS) == ''
    assert unconsumed_reason(topic, ['speed_scaling'], OVERRIDE_CONSUMERS) == ''
    assert unconsumed_reason(topic, ['hmi'], ()) == ''              # []: any reader acts
    assert 'nobody subscribes' in unconsumed_reason(topic, [], OVERRIDE_CONSUMERS)
    assert 'nobody subscribes' in unconsumed_reason(topic, [], ())
    said = unconsumed_reason(topic, ['hmi', 'recorder', 'hmi'], OVERRIDE_CONSUMERS)
    assert said.startswith('none of cobot_sim, speed_scaling (override_consumers)')
    assert 'only 3 reader(s) that cannot act on the arm (hmi, recorder)' in said
    # a consumer that is starting, not named by the graph yet: held, and said so
    said = unconsumed_reason(topic, ['_NODE_NAME_UNKNOWN_'], OVERRIDE_CONSUMERS)
    assert '(a node the graph does not name yet)' in said


def test_joint_names_given_twice_are_refused(setup):
    """A merged joint state naming a joint twice: the last copy was taken (a review's elbow read
    2.9 rad for 1.9), so SSM would see the arm where it is not. Now it is refused whole; a
    joint the arm ignores (a gripper's) may repeat."""
    bridge = Bridge(setup[0], setup[1], setup[2])
    names = list(JOINT_NAMES) + [JOINT_NAMES[2]]
    q = list(setup[0].poses['home']) + [setup[0].poses['home'][2] + 1.0]
    with pytest.raises(InputError, match=f'joint state names {JOINT_NAMES[2]} more than once'):
        bridge.joint_state(names, q, [0.0] * len(names), 0, 0)
    assert bridge.q is None
    names = list(JOINT_NAMES) + ['gripper_joint', 'gripper_joint']
    bridge.joint_state(names, q[:6] + [0.0, 0.1], [0.0] * len(names), 0, 0)
    np.testing.assert_array_equal(bridge.q, setup[0].poses['home'])


def test_a_velocity_no_arm_can_have_is_refused(setup):
    """A joint state whose velocity is finite but beyond any arm (an adversarial review: one
    of 1e18 rad/s swallowed the frozen-driver check's running sum, which then read no claim
    and let a frozen driver's stop clear) is refused whole, like a position beyond the
    limits; ten times a joint's limit is still taken (a driver's noise at speed)."""
    description = setup[0]
    bridge = Bridge(description, setup[1], setup[2])
    qd = np.zeros(6)
    qd[1] = 10.5 * description.velocity[1]
    with pytest.raises(InputError, match=f'{JOINT_NAMES[1]} velocity .* more than 10 times its '
                                         'limit'):
        bridge.joint_state(JOINT_NAMES, description.poses['home'], qd, 0, 0)
    assert bridge.q is None
    qd[1] = 9.5 * description.velocity[1]
    bridge.joint_state(JOINT_NAMES, description.poses['home'], qd, 0, 0)
    np.testing.assert_array_equal(bridge.qd, qd)


def test_after_a_clock_step_the_writers_that_restart_with_it_are_followed(setup):
    """A replay run again with sim time, a /clock that restarted: the clock steps back 9 s and
    the arm's driver and the decision node restart with it, numbering their messages from 1.
    Their writer lines' times lay in the clock's future: every joint state and action was a
    'second writer's' until the clock caught up (a review: still refused 2 s later)."""
    description, programs, arm = setup
    bridge = Bridge(description, programs, arm)
    home = description.poses['home']
    t = 100 * 10 ** 9
    for k in range(1, 30):
        bridge.joint_state(JOINT_NAMES, home, [0.0] * 6, t, t, sequence=k)
        bridge.check_writer('action', k, t)
        bridge.tick(t)
        t += 10 * MS
    t -= 9 * 10 ** 9
    assert 'the clock stepped back' in bridge.tick(t).reason
    for k in range(1, 30):                   # must not raise: the first writer heard is followed
        bridge.joint_state(JOINT_NAMES, home, [0.0] * 6, t, t, sequence=k)
        bridge.check_writer('action', k, t)
        command = bridge.tick(t)
        t += 10 * MS
    assert 'second writer' not in command.reason and 'joint state' not in command.reason, \
        command.reason
    assert bridge._hold_reason(t) == ''


def test_a_skeleton_that_jumps_away_is_not_trusted(setup):
    """A person near the arm; the next frame claims they are 2 m farther 10 ms later. SSM keeps
    the near body (aging) until it is older than human_timeout."""
    cell = Cell(setup, distance=1.5)
    program_running(cell)
    near = person(0.9)
    cell.run(0.3, body=lambda: seen(near))
    assert cell.commands[-1][0].stop                     # the person is at the arm
    steps = cell.run(0.3, body=lambda: seen(person(3.0)))
    assert all(c.stop for c, _, _ in steps)              # the jump is not trusted
    assert cell.bridge.counts['implausible_skeletons'] > 0
    assert min(c.separation.distance for c, _, _ in steps) < 0.6


def two(a, b) -> BodyCapsules:
    """A tracker's frame of two people (body_capsules over 64 keypoints)."""
    return body_capsules(np.concatenate([a, b]) + NOISE.normal(0.0, 0.0015, (64, 3)),
                         K4ABT_JOINTS)


def test_a_person_the_tracker_loses_near_the_arm_holds_it_until_seen_again(setup):
    """Two people, one 0.9 m from the base; the tracker drops the near one (occluded) and goes
    on with the far one. The frames without them are refused as jumps while the near one's
    frame is fresh; once it has aged out the arm must not resume: it holds, with the reason,
    until a frame shows two people again."""
    cell = Cell(setup, distance=1.5)
    program_running(cell)
    near, far = person(0.9), person(3.0, math.radians(60))
    cell.run(0.3, body=lambda: two(near, far))
    steps = cell.run(2.0, body=lambda: seen(far))          # the near person is gone from view
    # SSM goes on with their last frame while it is fresh, then the arm holds to the end
    aged = int((cell.description.ssm.human_timeout + 0.05) / 0.01)
    assert all(c.stop for c, _, _ in steps[aged:])
    assert 'the tracker lost a person' in steps[-1][0].reason
    assert 'a frame of 2 people became 1' in steps[-1][0].reason
    assert np.all(steps[-1][2] == 0)
    assert cell.bridge.counts['lost_people'] == 1
    # a third person walking in far away is not the lost one: the hold stays
    steps = cell.run(1.0, body=lambda: two(person(3.5, math.radians(-100)), far))
    assert cell.bridge.lost and all(c.stop for c, _, _ in steps)
    # seen again near the arm (where they were lost): the hold clears, SSM decides again,
    # and the arm resumes once they have stepped back
    cell.run(0.5, body=lambda: two(person(1.2), far))
    assert not cell.bridge.lost
    steps = cell.run(2.0, body=lambda: two(person(2.5), far))
    assert not steps[-1][0].stop


def test_a_person_dropped_from_the_frame_near_the_arm_holds_it_even_if_the_rest_is_plausible(
        setup):
    """The near person (0.9 m from the base) drops out and the one left is 1 m farther from
    the arm, which the jump gate takes as a walk at 3 m/s: a frame of fewer people whose
    nearest is farther lost someone near the arm, also across a frame of nobody."""
    for gap in (False, True):
        cell = Cell(setup, distance=1.5)
        program_running(cell)
        near, other = person(0.9), person(1.6, math.radians(-60))
        cell.run(0.3, body=lambda near=near, other=other: two(near, other))
        if gap:
            for _ in range(3):          # the tracker reports nobody for a few frames
                cell.bridge.skeleton(None, cell.t, cell.t)
        steps = cell.run(1.5, body=lambda other=other: seen(other))
        assert cell.bridge.lost and 'a frame of 2 people became 1' in steps[-1][0].reason
        assert all(c.stop for c, _, _ in steps[60:])


def test_the_operator_clears_a_lost_persons_hold_and_a_far_loss_holds_nothing(setup):
    cell = Cell(setup, distance=1.5)
    program_running(cell)
    near, far = person(0.9), person(3.0, math.radians(60))
    cell.run(0.3, body=lambda: two(near, far))
    cell.run(1.0, body=lambda: seen(far))
    assert cell.bridge.lost
    assert cell.bridge.clear_lost() and not cell.bridge.clear_lost()
    steps = cell.run(1.0, body=lambda: seen(far))
    assert not steps[-1][0].stop
    # a person lost 2.5 m from the arm (beyond lost_person_distance) is forgotten
    cell = Cell(setup, distance=2.5)
    program_running(cell)
    mid = person(2.5 + 0.5)
    cell.run(0.3, body=lambda: two(mid, far))
    steps = cell.run(1.5, body=lambda: seen(person(3.0, math.radians(80))))
    assert not cell.bridge.lost and cell.bridge.counts['lost_people'] == 0


# -- one action source -----------------------------------------------------------------------
def test_a_second_writer_of_the_actions_or_task_states_holds_the_arm(setup):
    cell = Cell(setup)
    program_running(cell)
    bridge = cell.bridge
    bridge.check_writer('action', 10, cell.t)           # the owner's line
    bridge.check_writer('action', 11, cell.t)
    with pytest.raises(InputError, match='second writer'):
        bridge.check_writer('action', 1, cell.t)        # another writer's numbers
    steps = cell.run(0.5)
    assert all(c.stop and 'second writer of hrc/action' in c.reason for c, _, _ in steps)
    assert np.all(cell.follower.qd == 0)
    cell.run(WRITER_HOLD)                               # silent for the hold: free again
    assert not cell.commands[-1][0].stop
    bridge.check_writer('task_state', 40, cell.t)
    with pytest.raises(InputError, match='second writer'):
        bridge.check_writer('task_state', 3, cell.t)
    assert 'hrc/task_state' in cell.run(0.05)[-1][0].reason
    cell.run(WRITER_HOLD)
    bridge.graph_hold('action', 'hrc/action has 2 publishers (/decision, /forger)')
    assert cell.run(0.05)[-1][0].reason == 'hrc/action has 2 publishers (/decision, /forger)'
    bridge.graph_hold('action', '')
    cell.run(0.5)
    assert not cell.commands[-1][0].stop


def test_a_goal_the_controller_dropped_is_sent_again_from_where_the_arm_stands(setup):
    """A controller that refused a forged goal holds the arm until a valid goal comes (as
    cobot_sim does): the bridge, commanding motion on an unfinished goal of its own while the
    arm stands for STALL_RESEND s, sends its goal again, and the program goes on."""
    cell = Cell(setup)
    program_running(cell)
    cell.follower.trajectory = None               # the controller dropped the goal: it holds
    sent = len([c for c, _, _ in cell.commands if c.trajectory is not None])
    steps = cell.run(2.0)
    again = [c.trajectory for c, _, _ in steps if c.trajectory is not None]
    assert len(again) == 1 and again[0].kind == 'program'
    assert sent >= 1 and cell.bridge.counts['goals_resent'] == 1
    assert np.max(np.abs(cell.follower.qd)) > 0.05        # moving again


def test_the_graphs_publishers_hold_the_arm_unless_the_owner_is_alone():
    from hrc_ros.core.robot.bridge import writers_reason
    assert writers_reason('/hrc/action', [], '/decision') == ''
    assert writers_reason('/hrc/action', ['/decision'], '/decision') == ''
    assert writers_reason('/hrc/action', ['/anyone'], '') == ''
    assert 'not by /decision' in writers_reason('/hrc/action', ['/forger'], '/decision')
    assert 'does not name' in writers_reason('/hrc/action', [None], '/decision')
    two = writers_reason('/hrc/action', ['/decision', None], '/decision')
    assert two.startswith('2 publishers of /hrc/action (/decision, a node the graph')


def test_the_check_against_the_true_body_counts_what_the_arm_did_near_the_person(setup):
    """core/robot/check.py on made-up records: a moving sample near the true body breaks SSM,
    the same sample with the arm at rest or the body far does not, a sample with no true
    body within a second is unchecked, one within a second but not 0.1 s is checked with the
    person that much nearer (cell_sim stalled once at load 9: the sample was left out), and
    the truth is interpolated between its samples."""
    from hrc_ros.core.robot.check import ssm_check
    description, _, arm = setup
    q = description.poses['home']
    qd = np.array([0.0, 0.5, 0.0, 0.0, 0.0, 0.0])          # 0.29 m/s at the fastest link
    near, far = person(0.9), person(3.0)    # S 0.51 m < S_p 0.65 m at that speed; S 2.4 m
    base = 10**12
    truth = [(base, near), (base + 20 * MS, near), (base + 400 * MS, far),
             (base + 420 * MS, far)]
    joints = [(base + 10 * MS, base + 10 * MS, q, qd),            # moving, the person near
              (base + 15 * MS, base + 15 * MS, q, np.zeros(6)),   # at rest: no check due
              (base + 410 * MS, base + 410 * MS, q, qd),          # moving, the person far
              (base + 900 * MS, base + 900 * MS, q, qd),          # far, 0.48 s after it
              (base + 2000 * MS, base + 2000 * MS, q, qd)]        # no true sample within 1 s
    separations = [(base + 10 * MS, [0.5] + [0.0] * 6 + [0.4, 0.2])]
    check = ssm_check(joints, truth, separations, description, arm)
    distance = arm.distance(q, body_capsules(near, K4ABT_JOINTS))
    assert distance < 1.0
    assert check['joint_states'] == 5 and check['moving'] == 4 and check['unchecked'] == 1
    assert check['bridged'] == 1                      # the far person 0.96 m nearer: no breach
    assert check['violations'] == 1 and check['worst']['separation_m'] == pytest.approx(distance)
    # a gap in the truth right after the near person: checked with them 0.26 m nearer still
    gap = ssm_check([(base + 150 * MS, 0, q, qd)], truth[:2], [], description, arm)
    assert gap['bridged'] == 1 and gap['unchecked'] == 0 and gap['violations'] == 1
    assert gap['worst']['separation_m'] == pytest.approx(distance - 2.0 * 0.13)
    assert check['own_moving'] == 1 and check['own_violations'] == 0
    # halfway between two true samples of a walking person: the body halfway
    walk = [(base, person(3.0)), (base + 20 * MS, person(1.0))]
    mid = ssm_check([(base + 10 * MS, base + 10 * MS, q, qd)], walk, [], description, arm)
    assert mid['min_separation_moving_m'] == pytest.approx(
        arm.distance(q, body_capsules(person(2.0), K4ABT_JOINTS)), abs=1e-9)


def test_an_arm_at_rest_when_a_person_appears_counts_in_the_appearance_until_they_are_seen():
    """bench/ssm_scenarios.py's appear episode 135 (seed 0, 15 epochs): the arm happened to
    stand when the person appeared and started again 60 ms later, before the frame showing them
    reached the bridge. Those samples are the appearance exception's (no monitor sees a person
    sooner than its sensor), not ordinary violations: the window closed at the first rest."""
    from hrc_ros.core.config import load_config
    from hrc_ros.core.mdp.policy import default_policy_path, load_policy
    from hrc_ros.core.model import HRCModel
    from hrc_ros.core.paths import arm_config_path
    from hrc_ros.core.robot.cell import ArmCell, person_seed
    from hrc_ros.core.study.evaluation import episodes_of
    config = load_config(arm_config_path())
    model = HRCModel(config)
    cell = ArmCell(model, load_policy(default_policy_path(config), config), person='appear')
    scenarios, seeds = episodes_of(model, 'random', 136, 15, 0, 0.5)
    result = cell.episode(scenarios[135], seeds[135], person_seed(0, 135), 'ssm_only')
    assert result.ssm_violations == 0 and result.contacts == 0
    assert result.appearance_violations > 0          # the arm moved by them, unseen
    assert result.rest_after_event > 0.06            # at rest after their frame arrived
    assert result.stop_delay == 0.0                  # stopped in the tick their frame came


def test_people_counts_the_bodies_of_a_frame_whatever_joints_it_names():
    """people() counts bodies by their bones' suffixes (a joint set without the pelvis has no
    torso bone: counting torsos found one person in two); unlabelled keypoints are one."""
    from hrc_ros.core.robot.arm import people
    upper = tuple(j for j in K4ABT_JOINTS if j != 'pelvis')
    for joints in (K4ABT_JOINTS, upper):
        for n in (1, 2, 5):
            points = NOISE.normal(0.0, 1.0, (n * len(joints), 3))
            assert people(body_capsules(points, joints)) == n
    assert people(body_capsules(NOISE.normal(0.0, 1.0, (64, 3)))) == 1
