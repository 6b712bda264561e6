"""People who test SSM, through the ROS graph: cobot_sim_node and robot_bridge_node as processes,
cell_sim_node's 3D person running a scenario of core/cell/scenarios.py (the batch's people:
hrc-evaluate --cell arm --person), and this test's node as the task manager and the decision
node, which keeps the arm on its program (ct, then nw every second) whatever the person does.

Each scenario's run is checked from outside: every joint state of the arm against the person's
true body at that instant (cell_sim's hrc/sim/true_skeleton, `core.robot.check`), and every
hrc/separation sample against the S_p cobot_sim published with it. The batch runs the same
scenarios by the thousand (bench/ssm_scenarios.py); here the graph's own timing (DDS, three
processes, a loaded machine) is what is tested.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Bool, Float64, Float64MultiArray, String, UInt8MultiArray

from hrc_ros.core.model import TASK_VARIABLES
from hrc_ros.core.robot.arm import Arm, body_capsules
from hrc_ros.core.robot.bridge import load_robot_description
from hrc_ros.core.robot.check import ssm_check
from hrc_ros.core.cell.tracking import K4ABT_JOINTS
from hrc_ros.ros import conversions as conv
from hrc_ros.ros import qos
from hrc_ros.ros.launch_plan import ROBOT_OVERRIDES
from hrc_ros.ros.processes import NodeProcesses
from spun import SpunNode

START_TIMEOUT = 90.0
RUN = 9.0            # s of each scenario after the person's clock starts (event in [2, 4] s)
WINDOW = 8.0         # cell_sim's scenario_window: the event is drawn in [2 s, 4 s]
DRIVER = 'robot_scenarios_test'
DESCRIPTION = load_robot_description()
DEEP = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100000,
                  reliability=ReliabilityPolicy.RELIABLE)
STREAM = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100000,
                    reliability=ReliabilityPolicy.BEST_EFFORT)


def task(**values) -> dict:
    return {**{name: 0 for name in TASK_VARIABLES}, **values}


class Driver(SpunNode):
    """The task manager and decision node of the run, and the recorder of the rest."""

    wait_timeout = 30.0

    def __init__(self):
        super().__init__(DRIVER)
        n = self.node
        self.lock = threading.Lock()
        self.joints, self.truth, self.separations, self.stops, self.statuses = [], [], [], [], []
        n.create_subscription(JointState, 'joint_states', self._joint, STREAM)
        n.create_subscription(PoseArray, 'hrc/sim/true_skeleton', self._truth, DEEP)
        n.create_subscription(Float64MultiArray, 'hrc/separation', self._separation, STREAM)
        self.overrides = []         # publication times (ns) of the bridge's overrides
        n.create_subscription(Float64, 'hrc/speed_override',
                              lambda m, info: self.overrides.append(
                                  int(info['source_timestamp'])), DEEP)
        n.create_subscription(Bool, 'hrc/protective_stop',
                              lambda m: self.stops.append((time.monotonic(), m.data)),
                              qos.LATCHED)
        n.create_subscription(DiagnosticArray, '/diagnostics',
                              lambda m: self.statuses.extend(m.status), DEEP)
        self.task_pub = n.create_publisher(UInt8MultiArray, 'hrc/task_state', qos.LATCHED)
        self.action_pub = n.create_publisher(String, 'hrc/action', qos.RELIABLE)
        self.first = True
        n.create_timer(1.0, self._epoch)
        self.start()

    def _epoch(self):
        """ct on the robot's own task, then nw while it runs: the arm keeps working."""
        if self.first:
            self.task_pub.publish(conv.task_state_to_msg(task(tp=1, tc=200, tx=0)))
            self.action_pub.publish(String(data='ct'))
            self.first = False
        else:
            self.task_pub.publish(conv.task_state_to_msg(task(tp=1, tc=200, tx=0, ty=2, bp=1,
                                                              bc=200)))
            self.action_pub.publish(String(data='nw'))

    def _joint(self, msg, info):
        stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
        with self.lock:
            self.joints.append((stamp, int(info['source_timestamp']), np.array(msg.position),
                                np.array(msg.velocity)))

    def _truth(self, msg):
        stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
        points = np.array([[p.position.x, p.position.y, p.position.z] for p in msg.poses])
        with self.lock:
            self.truth.append((stamp, points))

    def _separation(self, msg, info):
        with self.lock:
            self.separations.append((int(info['source_timestamp']), list(msg.data)))

    def moving(self) -> bool:
        with self.lock:
            return bool(self.joints) and float(np.max(np.abs(self.joints[-1][3]))) > 0.05

    def since(self, marks):
        """Copies of the records after `marks` (the lengths at an earlier moment)."""
        with self.lock:
            return (list(self.joints[marks[0]:]), list(self.truth[marks[1]:]),
                    list(self.separations[marks[2]:]))

    def marks(self):
        with self.lock:
            return len(self.joints), len(self.truth), len(self.separations)


@pytest.fixture(scope='module')
def graph(tmp_path_factory, ros_domain_id):
    folder = tmp_path_factory.mktemp('robot_scenarios')
    params = folder / 'params.yaml'
    params.write_text(yaml.safe_dump({
        '/**/robot_bridge': {'ros__parameters': {**ROBOT_OVERRIDES['robot_bridge'],
                                                 'action_source': f'/{DRIVER}',
                                                 'task_state_source': f'/{DRIVER}'}},
        '/**/cobot_sim': {'ros__parameters': ROBOT_OVERRIDES['cobot_sim']}}))
    suite = NodeProcesses(folder, [params])
    driver = Driver()
    try:
        suite.start('cobot_sim_node')
        suite.start('robot_bridge_node')
        yield driver, suite, folder
    finally:
        suite.stop(10.0)
        driver.close()


def run_scenario(graph, scenario: str, seed: int):
    """cell_sim with `scenario` for RUN s of its clock, the arm on its program; the records."""
    driver, suite, folder = graph
    assert not suite.dead(), suite.logs()
    person = NodeProcesses(folder, [])
    marks = driver.marks()
    try:
        person.start('cell_sim_node', name=f'cell_sim_{scenario}', ros_args=[
            '-p', 'person:=3d', '-p', f'person_scenario:={scenario}', '-p', f'seed:={seed}',
            '-p', f'scenario_window:={WINDOW}'])
        driver.first = True             # ct again: the program runs from this scenario's start
        driver.wait(lambda: (len(driver.truth) > marks[1] and driver.moving())
                    or person.dead() or suite.dead(),
                    'the person in the cell and the arm on its program', START_TIMEOUT)
        assert not person.dead() and not suite.dead(), person.logs() + suite.logs()
        began = time.monotonic()
        driver.wait(lambda: time.monotonic() - began > RUN or person.dead(), 'the scenario',
                    RUN + 30)
        assert not person.dead(), person.logs()
        assert person.stop(10.0) == {f'cell_sim_{scenario}': 0}, person.logs()
    finally:
        person.stop(5.0)
    assert not suite.dead(), suite.logs()

    def read_past_the_person() -> bool:
        """The joint states read up to the person's last true skeleton: a reader that lags
        takes one message per ready subscription in a wait, so the 125 Hz joint states are
        read behind the skeletons, and records copied at once missed the scenario's last
        samples (at load 9-11, none after a person appeared: 2026-12-07). cobot_sim goes on
        publishing after the person leaves."""
        with driver.lock:
            return (len(driver.truth) > marks[1] and len(driver.joints) > marks[0]
                    and driver.joints[-1][0] >= driver.truth[-1][0])
    driver.wait(read_past_the_person, 'the joint states read past the person', 60)
    joints, truth, separations = driver.since(marks)
    assert truth, 'cell_sim published no true skeleton'
    # the samples while the person was in the cell (after cell_sim stops the arm brakes on a
    # skeleton that ages out: nobody is there to check against)
    first, last = truth[0][0], truth[-1][0]
    return ([j for j in joints if first <= j[0] <= last], truth,
            [x for x in separations if first <= x[0] <= last])


def monitor_gap(driver, worst) -> float | None:
    """The longest the bridge went without sending an override (s) in the 0.3 s before the
    worst sample: a monitor the loaded machine stalled longer than cobot_sim's watchdog."""
    if not worst:
        return None
    t = worst['stamp_ns']
    sent = np.array(sorted(x for x in driver.overrides if t - 3 * 10**8 <= x <= t))
    return float(np.diff(sent).max() * 1e-9) if len(sent) > 1 else None


def nearest_approach(joints, truth) -> float:
    """The smallest true separation of the run (m), at the joint states' configurations."""
    arm = Arm()
    times = np.array([t for t, _ in truth])
    best = np.inf
    for stamp, _, q, _ in joints[::5]:
        i = int(np.clip(np.searchsorted(times, stamp), 0, len(truth) - 1))
        best = min(best, arm.distance(q, body_capsules(truth[i][1], K4ABT_JOINTS)))
    return best


@pytest.mark.parametrize('scenario, seed', [('frozen_tracker', 3), ('reach', 1)])
def test_ssm_holds_against_the_true_body_when_a_person_walks_in_or_reaches(graph, scenario,
                                                                           seed):
    """A walk-in at 1.6 m/s whose tracker freezes mid-walk (the skeleton keeps coming, fresh
    stamps, the same keypoints), and a reach over the table at 2.0 m/s: no joint state with
    the arm moving has S < S_p by the true body, nor by cobot_sim's own hrc/separation."""
    driver = graph[0]
    since = len(driver.statuses)
    joints, truth, separations = run_scenario(graph, scenario, seed)
    check = ssm_check(joints, truth, separations, DESCRIPTION)
    assert check['moving'] > 100, check         # the arm worked during the run
    assert check['unchecked'] == 0, check
    assert check['violations'] == 0, (check['worst'], monitor_gap(driver, check['worst']),
                                      check)
    assert check['own_violations'] == 0, (check['own_min_margin_m'], check)
    # the person did come to the arm: the hazard happened
    assert nearest_approach(joints, truth) < 0.35
    for _, _, q, _ in joints:                   # the arm stayed within its joint limits
        assert DESCRIPTION.outside(q) == ''
    if scenario == 'frozen_tracker':
        reasons = [conv.diagnostic_values(s).get('stop_reason', '')
                   for s in driver.statuses[since:] if s.name == 'robot_bridge: bridge']
        assert any('frozen tracker' in r for r in reasons), set(reasons)


def test_a_person_who_appears_at_the_arm_stops_it_at_once(graph):
    """A second person appears 0.25 m from the arm's links (inside S_p(0): no monitor can stop
    in time for them): the bridge's protective stop follows their first skeleton at once, and
    every sample outside the appearance (until the arm is at rest) keeps SSM."""
    joints, truth, separations = run_scenario(graph, 'appear', 2)
    first = next(i for i, (_, points) in enumerate(truth) if len(points) > len(K4ABT_JOINTS))
    appeared, alone = truth[first][0], truth[first - 1][0]   # between these two true samples
    later = [(t, float(np.max(np.abs(qd)))) for t, _, _, qd in joints if t > appeared]
    rest = next((t for t, speed in later if speed == 0.0), None)
    # failed once at load 9 (CI bench, 2026-12-07) with no sample at rest after the appearance,
    # whose bridge log showed the stop: what the driver had then, to tell lost samples from
    # an arm that went on
    assert rest is not None, (
        f'no joint state at rest after the appearance ({appeared * 1e-9:.3f} s): '
        f'{len(later)} samples after it, the last at {later[-1][0] * 1e-9:.3f} s' if later else
        'none after it', f'slowest {min(v for _, v in later):.4f} rad/s' if later else '',
        f'truth until {truth[-1][0] * 1e-9:.3f} s', monitor_gap(graph[0], {'stamp_ns': appeared}),
        [(round(t * 1e-9, 3), round(v, 4)) for t, v in later[:: max(1, len(later) // 20)]],
        graph[1].logs())
    before = [j for j in joints if j[0] <= alone]
    after = [j for j in joints if j[0] > rest]
    for part in (before, after):
        check = ssm_check(part, truth, separations, DESCRIPTION)
        assert check['violations'] == 0 and check['unchecked'] == 0, (
            part is after, check['worst'], monitor_gap(graph[0], check['worst']), check)
    assert ssm_check(before, truth, separations, DESCRIPTION)['moving'] > 50
    # the arm came to rest in its braking time from at most 1 m/s at 2 m/s^2, and the
    # latency of one skeleton (20 ms at cell_sim's 50 Hz) and a few DDS hops
    assert (rest - appeared) * 1e-9 < 0.5 + 0.25
