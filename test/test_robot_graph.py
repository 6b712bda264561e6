"""The graph with the arm, ROS-free: the rules the nodes of docs/ROBOT.md 5 add to the cell.

- the task manager's `robot_progress` (`core.protocol.TaskEpochs`): the robot's counter bc
  runs down in an epoch only when the bridge's progress, published before the epoch's end,
  shows a cycle bc has not counted (the batch cell's `robot_cycle_done`);
- the estimator's `distance_source: arm_links` (`core.robot.links.LinkDistance`): d is the band
  of the separation between the arm's links at its latest joint state and the person's body
  capsules; without a fresh arm state d = 0 (the fail-safe), with the reason; as a node over
  DDS too;
- the view with the arm, the batch's pre-roll, and the refusals of what the graph cannot run.
"""

import math
import time

import numpy as np
import pytest

from hrc_ros.core.cell.person import SimulatedPerson
from hrc_ros.core.cell.tracking import K4ABT_JOINTS
from hrc_ros.core.decision.observation import distance_level
from hrc_ros.core.model import CT, NW, TASK_VARIABLES, HRCModel
from hrc_ros.core.protocol import InputError, Stamp, TaskEpochs
from hrc_ros.core.robot.arm import JOINT_NAMES, Arm
from hrc_ros.core.robot.bridge import load_robot_description
from hrc_ros.core.robot.links import LinkDistance
from hrc_ros.core.tasks import TaskBook, robot_cycle_done

MS = 1_000_000
SEED = 26       # the seed of the case study with the arm (test_robot_case_study.py)
TIMEOUT = 250 * MS


@pytest.fixture(scope='module')
def model(default_config):
    return HRCModel(default_config)


def bc_of(step):
    return None if step.task_state is None else step.task_state['bc']


def test_the_physical_progress_rule_counts_each_completed_cycle_once():
    # a task of 3 cycles: bc = 3 after the commit, then one per cycle completed
    assert not robot_cycle_done(3, 0, 3)          # nothing done yet
    assert robot_cycle_done(3, 1, 3)              # the first cycle: 3 -> 2
    assert not robot_cycle_done(3, 1, 2)          # the same cycle is not counted twice
    assert robot_cycle_done(3, 3, 2)              # two more done: one a epoch, 2 -> 1
    assert robot_cycle_done(3, 3, 1) and not robot_cycle_done(3, 3, 0)


def run_epochs(tasks, actions, progress):
    """Epochs 1.. at 1 s; `progress` = [(published_ms, (nature, cycles, done))] fed before
    each signal they precede. Returns bc of every epoch's task state."""
    out, fed = [], 0
    for k in range(1, len(actions) + 2):
        t = (k - 1) * 1000 * MS
        while fed < len(progress) and progress[fed][0] * MS < t:
            tasks.robot_progress_received(*progress[fed][1], progress[fed][0] * MS)
            fed += 1
        out.append(bc_of(tasks.epoch(k, Stamp(t, k), t)))
        if k <= len(actions):
            tasks.action(actions[k - 1], t + 10 * MS, t + 11 * MS)
    return out


def test_without_robot_progress_bc_runs_by_the_model(model):
    tasks = TaskEpochs(TaskBook(model, initial_task=(1, 2, 0)), TIMEOUT)
    # ct commits (bc = tc = 2), then every nw runs bc down, whatever the arm does
    assert run_epochs(tasks, [CT, NW, NW], [(1500, (0, 2, 0))]) == [0, 2, 1, 0]


def test_with_robot_progress_bc_follows_the_cycles_the_arm_completed(model):
    tasks = TaskEpochs(TaskBook(model, initial_task=(1, 2, 0)), TIMEOUT, robot_progress=True)
    # epoch 1 ct; the bridge starts the run (0 of 2) in epoch 1, completes cycle 1 in epoch
    # 2, nothing in epoch 3 (SSM held the arm), cycle 2 in epoch 4
    progress = [(300, (0, 2, 0)), (1700, (0, 2, 1)), (3400, (0, 2, 2))]
    assert run_epochs(tasks, [CT, NW, NW, NW], progress) == [0, 2, 1, 1, 0]
    assert tasks.book.completed and tasks.book.completed[0].complete_epoch == 4
    assert tasks.status()['robot_progress'] == (0, 2, 2)


def test_progress_counts_by_its_publication_time_not_its_arrival(model):
    tasks = TaskEpochs(TaskBook(model, initial_task=(1, 2, 0)), TIMEOUT, robot_progress=True)
    tasks.epoch(1, Stamp(0, 1), 0)
    tasks.action(CT, 10 * MS, 11 * MS)
    tasks.robot_progress_received(0, 2, 0, 300 * MS)
    assert bc_of(tasks.epoch(2, Stamp(1000 * MS, 2), 1000 * MS)) == 2
    # epoch 3's signal comes first; the action of epoch 2 is late, and so is a progress
    # published before the signal: it counts. One published after the signal does not.
    assert tasks.epoch(3, Stamp(2000 * MS, 3), 2000 * MS).task_state is None
    tasks.robot_progress_received(0, 2, 2, 2005 * MS)        # epoch 3's, delivered first
    tasks.robot_progress_received(0, 2, 1, 1990 * MS)        # epoch 2's, overtaken
    assert tasks.progress_at(2000 * MS) == (0, 2, 1)
    assert bc_of(tasks.action(NW, 1010 * MS, 2010 * MS)) == 1
    # epoch 3 ends with both cycles done: bc 1 -> 0, the task completes
    tasks.action(NW, 2020 * MS, 2021 * MS)
    assert bc_of(tasks.epoch(4, Stamp(3000 * MS, 4), 3000 * MS)) == 0


def test_no_share_or_no_progress_is_no_robot_work(model):
    for progress in ([], [(300, (0, 0, 0))]):     # nothing published; cycles 0: no share
        tasks = TaskEpochs(TaskBook(model, initial_task=(1, 2, 0)), TIMEOUT,
                           robot_progress=True)
        assert run_epochs(tasks, [CT, NW, NW], progress) == [0, 2, 2, 2]
    state = tuple(tasks.book.state[n] for n in TASK_VARIABLES)
    assert state[3] == 2 and state[7] == 2        # committed, bc untouched


# -- the estimator's arm_links ----------------------------------------------------------------
RADII = (0.2, 0.6, 1.2)
S = 1_000_000_000


@pytest.fixture(scope='module')
def description():
    return load_robot_description()


@pytest.fixture(scope='module')
def arm():
    return Arm()


def person_at(rho):
    """The simulated person at their workstation, pelvis `rho` m from the base axis."""
    person = SimulatedPerson(1, seed=0)          # hands on the table
    person.theta = person.theta_target = math.radians(-31.0)
    person.rho = rho
    return person.keypoints()


def test_d_is_the_band_of_the_separation_to_the_arms_links(description, arm):
    links = LinkDistance(description, RADII, K4ABT_JOINTS, arm)
    far = person_at(1.9)
    # by the reference point (the base) this person is in the outer band ...
    assert distance_level(far, (0, 0, 0), RADII) == 3
    poses = description.poses
    # ... by the links: 1.06 m from the arm at home (middle), 0.70 m at the collaboration pose
    # over their station (middle), 1.23 m folded back in the retreat pose (outer)
    for pose, band in (('home', 2), ('collaboration', 2), ('retreat', 3)):
        links.joint_state(JOINT_NAMES, poses[pose], 1 * S, 1 * S)
        level = links.level(far, 1 * S + 50_000_000)
        assert (level.d, level.reason) == (band, ''), pose
        assert level.separation.distance == pytest.approx(
            arm.distance(poses[pose], links_body(far)), abs=1e-12)
    # at the table's edge the arm over the station is 0.24 m away: the inner band, 1
    links.joint_state(JOINT_NAMES, poses['collaboration'], 2 * S, 2 * S)
    assert links.level(person_at(1.35), 2 * S).d == 1
    # the joints in another order (a driver's), a gripper joint besides: the same arm
    order = [5, 3, 1, 0, 2, 4]
    links.joint_state([JOINT_NAMES[i] for i in order] + ['gripper'],
                      [poses['retreat'][i] for i in order] + [0.5], 3 * S, 3 * S)
    assert links.level(far, 3 * S).d == 3


def links_body(points):
    from hrc_ros.core.robot.arm import body_capsules
    return body_capsules(points, K4ABT_JOINTS)


def test_without_a_fresh_arm_state_d_is_the_collision_level(description, arm):
    links = LinkDistance(description, RADII, K4ABT_JOINTS, arm)
    far = person_at(3.0)
    level = links.level(far, 1 * S)                     # never a joint state
    assert (level.d, level.separation) == (0, None)
    assert level.reason == 'no joint state of the arm yet'
    links.joint_state(JOINT_NAMES, description.poses['home'], 1 * S, 1 * S)
    # by the stamps: the skeleton 0.1 s after the arm's state is still fresh ...
    assert links.level(far, 1 * S + 100_000_000).d == 3
    assert links.level(far, 1 * S - 500_000_000).d == 3      # (an arm state newer than it)
    level = links.level(far, 1 * S + 150_000_000)            # ... 0.15 s after it is not
    assert level.d == 0 and '0.150 s older than the skeleton' in level.reason
    assert 'joint_state_timeout 0.1 s' in level.reason


def test_a_refused_arm_state_keeps_the_last_good_one(description, arm):
    links = LinkDistance(description, RADII, K4ABT_JOINTS, arm)
    home = description.poses['home']
    links.joint_state(JOINT_NAMES, home, 5 * S, 5 * S)
    bad = (
        (JOINT_NAMES[:5], home[:5], 'without wrist_3_joint'),
        (JOINT_NAMES, np.where(np.arange(6) == 2, np.nan, home), 'elbow_joint is nan'),
        (JOINT_NAMES, np.where(np.arange(6) == 2, 4.0, home), 'outside its limits'),
    )
    for names, positions, why in bad:
        with pytest.raises(InputError, match=why):
            links.joint_state(names, positions, 6 * S, 6 * S)
        assert links.stamp_ns == 5 * S and np.array_equal(links.q, home)
    with pytest.raises(InputError, match='older than the one held'):
        links.joint_state(JOINT_NAMES, description.poses['retreat'], 4 * S, 6 * S)
    # stamped ahead of the reader's clock: it would pair with skeletons after the arm stopped
    with pytest.raises(InputError, match='arm joint state stamped 1.000 s ahead'):
        links.joint_state(JOINT_NAMES, description.poses['retreat'], 7 * S, 6 * S)
    assert np.array_equal(links.q, home)
    with pytest.raises(InputError, match='not whole bodies'):      # 7 keypoints, 32 names
        links.level(np.zeros((7, 3)) + 1.0, 5 * S)
    # an unlabelled skeleton: a sphere around each keypoint
    spheres = LinkDistance(description, RADII, None, arm)
    spheres.joint_state(JOINT_NAMES, home, 5 * S, 5 * S)
    # the closest part is a hand tip: its 0.1 m sphere reaches 5 cm nearer than the hand's
    # 0.05 m capsule (1.011 m, not 1.061 m)
    bones = links.level(person_at(1.9), 5 * S).separation.distance
    level = spheres.level(person_at(1.9), 5 * S)
    assert level.d == 2 and level.separation.distance == pytest.approx(bones - 0.05)


# -- the view with the arm --------------------------------------------------------------------
def test_the_view_draws_the_arm_its_ssm_shell_the_body_and_the_separation(description, arm):
    from hrc_ros.core.cell.view import LEVEL_COLORS, CellView, scene
    from hrc_ros.core.robot.arm import body_capsules
    q = description.poses['collaboration']
    keypoints = person_at(1.35)
    body = body_capsules(keypoints, K4ABT_JOINTS)
    sep = arm.separation(q, body)
    view = CellView()
    view.feed('arm', (arm.segments(q), arm.radii), 0.0)
    view.feed('skeleton', keypoints, 0.0)
    view.feed('body', (body.segments, body.radii), 0.0)
    view.feed('separation', {'S': sep.distance, 'arm': sep.arm_point,
                             'human': sep.human_point, 'S_p': 0.3}, 0.0)
    shapes = scene(view.state, RADII, (0, 0, 0))
    by_ns = {}
    for shape in shapes:
        by_ns.setdefault(shape.ns, []).append(shape)
    # no circles around the base: with the arm, d is the band of the separation
    assert 'safety' not in by_ns and 'closest' not in by_ns
    assert len(by_ns['arm']) == 2 * len(arm.radii) and len(by_ns['body']) == 2 * len(body.radii)
    lines = [s for s in by_ns['arm'] if s.kind == 'line']
    assert [s.scale[0] for s in lines] == pytest.approx(2 * arm.radii)
    np.testing.assert_allclose(np.stack([s.points for s in lines]), arm.segments(q))
    shell = [s for s in by_ns['ssm_shell'] if s.kind == 'line']
    assert [s.scale[0] for s in shell] == pytest.approx(2 * (arm.radii + 0.3))
    assert all(s.color[3] < 0.2 for s in by_ns['ssm_shell'])          # translucent
    segment = next(s for s in by_ns['separation'] if s.kind == 'line')
    np.testing.assert_allclose(segment.points, [sep.arm_point, sep.human_point])
    text = next(s for s in by_ns['separation'] if s.kind == 'text').text
    assert text == f'S {sep.distance:.2f} m (inner)  S_p 0.30 m'
    assert by_ns['body'][0].color[:3] == LEVEL_COLORS[1]              # S 0.24 m: inner
    # without the arm's state the picture is the reference point's, as before
    assert 'safety' in {s.ns for s in scene(CellView().state, RADII, (0, 0, 0))}


def test_the_nodes_refuse_a_person_source_or_fault_they_cannot_run():
    from hrc_ros.ros.nodes import belief_estimator_node, cell_sim_node
    assert cell_sim_node.check_parameters({'person': '3d', 'faults': ['dropout:3']}) is None
    assert 'collision needs person' in cell_sim_node.check_parameters(
        {'person': '3d', 'faults': ['collision:3']})
    assert "person must be point or 3d, got 'ghost'" in cell_sim_node.check_parameters(
        {'person': 'ghost'})
    assert 'distance_source must be reference_point or arm_links' in \
        belief_estimator_node.check_parameters({'distance_source': 'gps'})
    assert 'keypoint_joints' in belief_estimator_node.check_parameters(
        {'keypoint_joints': ['pelvis', 'tail']})


def test_the_case_study_refuses_the_arm_with_the_synthetic_tracker(tmp_path):
    import subprocess
    import sys
    proc = subprocess.run([sys.executable, '-m', 'hrc_ros.ros.case_study', '--out',
                           str(tmp_path / 'out'), '--robot', 'sim', '--input', 'body_tracking'],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert proc.stderr.startswith("hrc-case-study: error: robot 'sim' with body_tracking")
    assert len(proc.stderr.strip().splitlines()) == 1 and not (tmp_path / 'out').exists()


def test_the_batch_pre_roll_starts_the_first_epoch_out_of_ssms_start_up_stop(model):
    """ArmCellSettings.pre_roll: the bridge runs before epoch 1 (as a graph's does), so it has
    left its start-up protective stop (resume_time 0.2 s) when a_1 comes; the arm holds
    meanwhile (no action yet)."""
    from hrc_ros.core.mdp.policy import default_policy_path, load_policy
    from hrc_ros.core.robot.cell import ArmCell, ArmCellSettings
    from hrc_ros.core.study.simulation import Scenario
    policy = load_policy(default_policy_path(), model.config)
    # a robot task waiting (2 epochs at its own station), the person in the outer circle: SSM's
    # start-up stop is its resume_time alone (a person at the table has their hands at the
    # arm's protective distance at the slowest motion, and the tracker's jitter holds the arm
    # on and off), and ssm_only commits to the task at once
    one = Scenario((0, 0, 1, 2, 0, 0, 0, 0, 0, 0, 3), (), 1, 'epoch 1')
    home = load_robot_description().poses['home']
    runs = {}
    for pre_roll in (0.0, 1.0):
        cell = ArmCell(model, policy, settings=ArmCellSettings(pre_roll=pre_roll))
        runs[pre_roll] = cell.episode(one, SEED, [SEED, 2], 'ssm_only', record=True)
    assert runs[0.0].actions == runs[1.0].actions == ['ct']
    assert runs[0.0].stop_time == pytest.approx(0.2)         # resume_time, in epoch 1
    assert runs[1.0].stop_time == 0.0
    assert np.array_equal(runs[1.0].arm_path[0][1], home)     # it held through the pre-roll
    # so the program starts earlier: 0.3 s in, the arm has gone farther
    moved = {p: np.abs(r.arm_path[15][1] - home).max() for p, r in runs.items()}
    assert moved[1.0] > moved[0.0] > 0
    with pytest.raises(ValueError, match='pre_roll'):
        ArmCellSettings(pre_roll=-1.0)



# -- the estimator node with arm_links, over DDS ----------------------------------------------
@pytest.fixture()
def graph():
    from test_nodes import Graph
    graph = Graph()
    yield graph
    graph.close()


def test_the_estimator_node_takes_d_from_the_arms_links_and_fails_safe_without_them(
        graph, description):
    from sensor_msgs.msg import JointState
    from test_nodes import Estimator

    from hrc_ros.ros import conversions as conv
    from hrc_ros.ros import qos
    est = Estimator(graph, distance_source='arm_links', keypoint_joints=list(K4ABT_JOINTS))
    arm_pub = graph.publisher(JointState, 'joint_states', qos.SENSOR_DATA)
    far = person_at(1.9)           # outer by the base, 0.70 m from the arm over its station
    collaboration = description.poses['collaboration']

    # the skeleton stamped `later` s after the arm's last state, not by the clock when it is
    # sent: under load the sends between them took more than joint_state_timeout (the
    # estimator read the arm 0.124 s older than the skeleton: d 0 for 2, 2026-12-07)
    arm_time = [time.time()]

    def arm(q):
        arm_time[0] = time.time()
        est.send('arm_joint_states', arm_pub, conv.joint_state_to_msg(
            JOINT_NAMES, np.zeros(6), q, conv.seconds_to_stamp(arm_time[0])))

    def skeleton(later=0.0):
        est.send('skeleton', est.skeleton,
                 conv.keypoints_to_msg(far, conv.seconds_to_stamp(arm_time[0] + later)))
    arm(collaboration)
    est.motion(1)
    skeleton()
    est.epoch(1)
    assert est.distances[-1].data == 2
    assert est.node.separation == pytest.approx(0.704, abs=0.01)
    arm(description.poses['retreat'])               # folded away: the outer band
    est.motion(1)
    skeleton()
    est.act('nw')
    est.epoch(2)
    assert est.distances[-1].data == 3
    # the arm's stream stops: the next skeleton is 0.5 s newer than its last state
    est.motion(1)
    skeleton(later=0.5)
    est.act('nw')
    est.epoch(3)
    assert est.distances[-1].data == 0
    warn = graph.diagnostics('belief_estimator: arm links', level=b'\x01')
    assert warn and 'older than the skeleton' in warn[-1].message
    arm(collaboration)                                # back
    est.motion(1)
    skeleton()
    est.act('dn')
    est.epoch(4)
    assert est.distances[-1].data == 2
    assert graph.spin_until(lambda: graph.diagnostics('belief_estimator: arm links',
                                                      level=b'\x00'))
