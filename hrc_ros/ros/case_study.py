"""hrc-case-study: the paper's case study end to end through the ROS 2 nodes.

    hrc-case-study --out out/case_study [--epochs 20] [--epoch-period 0.5] [--seed 0]
        [--input joint_states|body_tracking] [--no-view] [--hmi [show|answers]]
        [--robot none|sim]

What it does, as a user would by hand:

1. writes the case study's node parameters (`case_study_params.yaml`, from
   `core.study.simulation.case_study()`, the scenario's one definition) and the run's own
   (`run_params.yaml`) into the output folder, loaded in that order after the shipped
   `hrc_params.yaml`;
2. starts `cell_sim_node`, `task_manager_node`, `belief_estimator_node`, `cell_view_node`
   (unless --no-view) and then `decision_node` as separate processes (their console scripts),
   each logging to `logs/<node>.log`, and waits until the graph shows them. With
   `--input body_tracking` the simulated human's motion reaches the estimator through a body
   tracker's stream instead: `cell_sim_node`'s motion is remapped to `sim/human/*`,
   `tracker_sim_node` turns it into an Azure Kinect body-tracking stream and
   `body_tracking_node` reads that back into `human/*` (with
   `config/body_tracking_sim_params.yaml`);
3. records every hrc topic into a rosbag2-compatible MCAP bag (`bag/`) while it watches the
   run over DDS, until the decision node has acted in the last epoch;
4. stops the nodes (SIGINT to each process group, one after the other, the decision node first,
   each once the one before has exited: `processes.NodeProcesses.stop`) and prints the trajectory
   as the paper's Table 6: per epoch the true state (hidden emotions from the simulated cell's
   debug topic `hrc/sim/true_state`, task and activity from `hrc/task_state`, distance), the
   observation, the belief and the action; writes it as CSV and the plots of `hrc-simulate`.

The trajectory is assembled by publication time around the epoch signals (`assemble`).

`--robot sim` runs the cell with the arm (docs/ROBOT.md, "the graph with the arm"): it also
starts `cobot_sim_node` (a simulated UR5e) and `robot_bridge_node` (the actions into its motion
under speed and separation monitoring) before the decision node, with the parameters of
`launch_plan.ROBOT_OVERRIDES` (d from the arm's links, the robot's counter from its program's
progress, the 3D person), an epoch of 1 s unless `--epoch-period` says otherwise (the batch
cell's physical epoch), and records the bridge's goals, the arm's joint states,
`hrc/separation`, the speed override, the protective stop and the progress in the bag.

`--hmi` also starts `hmi_node` (docs/HMI.md) on ``http://127.0.0.1:<--hmi-port>/``: with `show`
(the default) the simulated person keeps answering the robot's requests and the page only shows
them, so the run stays the seeded, reproducible one; with `answers` the simulated person stops
answering (`cell_sim` `answer_requests: false`) and a person answers on the page (give them
time: `--epoch-period 5`).
"""

from __future__ import annotations

import os
import shutil
import socket
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from ..core.cell.scenarios import SCENARIOS as PERSON_SCENARIOS
from ..core.config import BELIEF_MODES, ConfigError, load_config
from ..core.cell.faults import parse_faults
from ..core.model import ACTIONS, STATE_VARIABLES, TASK_VARIABLES, HRCModel
from ..core.paths import (arm_config_path, default_config_path, folder_target, share_dir,
                          write_text)
from ..core.study.plots import plot_trajectory
from ..core.mdp.policy import PolicyError, default_policy_path, load_policy
from ..core.learning.recordings import place_in_epochs
from ..core.study.simulation import (BELIEF_COLUMNS, SCORE_COLUMNS, Scenario, Trajectory,
                                     case_study, check_model_cell)
from ..core.tasks import TaskBook
from ..core.decision.selection import POMDP_SELECTORS, SELECTORS
from ..core.pomdp.policy import load_shipped_pomdp_policy
from ..tools.common import (MAX_SEED, Parser, ToolError, bounded_float, bounded_int, fail,
                            output_folder, path_text)
from ..core.protocol import TaskEpochs
from .launch_plan import (BODY_TRACKING_SIM_PARAMS, ROBOT_OVERRIDES, ROBOTS, SIM_MOTION_REMAPS,
                          SYNTHETIC_TRACKER_WITH_ARM, scenario_parameters)
from . import stop
from .processes import NodeProcessError, NodeProcesses

NODE_NAMES = {'cell_sim_node': 'cell_sim', 'task_manager_node': 'task_manager',
              'belief_estimator_node': 'belief_estimator', 'decision_node': 'decision',
              'cell_view_node': 'cell_view', 'tracker_sim_node': 'tracker_sim',
              'body_tracking_node': 'body_tracking', 'hmi_node': 'hmi',
              'cobot_sim_node': 'cobot_sim', 'robot_bridge_node': 'robot_bridge'}
INPUTS = ('joint_states', 'body_tracking')
ROBOT_TOPICS = {
    'joint_trajectory_controller/joint_trajectory': 'trajectory_msgs/msg/JointTrajectory',
    'joint_states': 'sensor_msgs/msg/JointState',
    'hrc/separation': 'std_msgs/msg/Float64MultiArray',
    'hrc/speed_override': 'std_msgs/msg/Float64',
    'hrc/protective_stop': 'std_msgs/msg/Bool',
    'hrc/robot_progress': 'std_msgs/msg/UInt8MultiArray',
    'hrc/sim/true_skeleton': 'geometry_msgs/msg/PoseArray',
}
ROBOT_EPOCH_PERIOD = 1.0    # s, the batch cell's physical epoch (ArmCellSettings)
# The case study with the arm (docs/ROBOT.md 6): the robot's share of a task advances only by
# program cycles the arm completes under SSM, so its three tasks take longer than the model's
# 20 epochs; in the batch cell the shipped arm policy completes them by epoch 31 with seed 0.
ROBOT_EPOCHS = 40
SSM_CHECK = 'ssm_check.json'    # written by a run with the arm only
TOPICS = {
    'human/joint_states': 'sensor_msgs/msg/JointState',
    'human/skeleton': 'geometry_msgs/msg/PoseArray',
    'hrc/observation': 'std_msgs/msg/UInt8',
    'hrc/distance_level': 'std_msgs/msg/UInt8',
    'hrc/belief': 'std_msgs/msg/Float64MultiArray',
    'hrc/task_request': 'std_msgs/msg/UInt8MultiArray',
    'hrc/human_response': 'std_msgs/msg/Bool',
    'hrc/task_state': 'std_msgs/msg/UInt8MultiArray',
    'hrc/action': 'std_msgs/msg/String',
    'hrc/epoch': 'std_msgs/msg/UInt32',
    'hrc/sim/true_state': 'std_msgs/msg/UInt8MultiArray',
    '/diagnostics': 'diagnostic_msgs/msg/DiagnosticArray',
    'hrc/task_request_result': 'diagnostic_msgs/msg/DiagnosticStatus',
}
VIEW_TOPICS = {'hrc/markers': 'visualization_msgs/msg/MarkerArray'}
BODY_TRACKING_TOPICS = {'body_tracking_data': 'visualization_msgs/msg/MarkerArray'}
WATCHED = ('hrc/epoch', 'hrc/task_state', 'hrc/observation', 'hrc/distance_level',
           'hrc/belief', 'hrc/action', 'hrc/human_response', 'hrc/sim/true_state')
ROBOT_WATCHED = ('hrc/robot_progress',)
LATCHED_TOPICS = ('hrc/task_state', 'hrc/distance_level', 'hrc/belief', 'hrc/sim/true_state')


MAX_RUN_EPOCHS = 10_000   # 83 minutes at the default period


class CaseStudyError(RuntimeError):
    pass


class Interrupted(Exception):
    """A stop signal (Ctrl-C) ended the run before its last epoch."""


def cell_nodes(args) -> list[str]:
    """The node processes of the run, in start order, the decision node last."""
    return (['cell_sim_node', 'task_manager_node', 'belief_estimator_node']
            + ['cell_view_node'] * args.view
            + ['tracker_sim_node', 'body_tracking_node'] * (args.input == 'body_tracking')
            + ['hmi_node'] * bool(args.hmi)
            + ['cobot_sim_node', 'robot_bridge_node'] * (args.robot == 'sim')
            + ['decision_node'])


def recorded_topics(args) -> dict[str, str]:
    return {**TOPICS, **(VIEW_TOPICS if args.view else {}),
            **(BODY_TRACKING_TOPICS if args.input == 'body_tracking' else {}),
            **(ROBOT_TOPICS if args.robot == 'sim' else {})}


def write_scenario_params(path: Path, scenario: Scenario) -> Path:
    """The scenario's node parameters (`launch_plan.scenario_parameters`) as a params file."""
    write_text(path, SCENARIO_HEADER + yaml.safe_dump(scenario_parameters(scenario),
                                                      sort_keys=False, default_flow_style=None))
    return path


SCENARIO_HEADER = """\
# The case study of hrc_ros.core.study.simulation.case_study() as node parameters, written
# by hrc-case-study (config/case_study_params.yaml holds the same for ros2 launch).
"""


def write_run_params(path: Path, args) -> Path:
    params = {
        '/**': {'ros__parameters': {'config': args.config or ''}},
        '/**/decision': {'ros__parameters': {
            # most of the epoch for its inputs (they normally take milliseconds): a scheduling
            # stall on a loaded machine must not turn into a fail-safe dn
            'epoch_period': args.epoch_period, 'input_timeout': 0.8 * args.epoch_period,
            # every listener that must not miss epoch 1: the task manager, the belief
            # estimator, this observer and the view
            'min_epoch_subscribers': 3 + bool(args.view),
            # ... each of them with its own reader matched to the clock (hrc/_epoch_ready)
            'min_epoch_ready': 3 + bool(args.view),
            'selector': args.selector,
            'policy': args.policy or ''}},
        '/**/cell_sim': {'ros__parameters': {'seed': args.seed}},
        '/**/belief_estimator': {'ros__parameters': {'belief_mode': args.belief_mode}},
    }
    if args.faults:   # rcl cannot type an empty list: leave the node's default then
        params['/**/cell_sim']['ros__parameters']['faults'] = list(args.faults)
    if args.hmi:      # show: the page shows the simulated answers; answers: the page gives them
        params['/**/hmi'] = {'ros__parameters': {'port': args.hmi_port,
                                                 'worker_answers': args.hmi == 'answers'}}
        params['/**/cell_sim']['ros__parameters']['answer_requests'] = args.hmi != 'answers'
    if args.robot == 'sim':
        for name, values in ROBOT_OVERRIDES.items():
            key = f'/**/{name}'
            params.setdefault(key, {'ros__parameters': {}})['ros__parameters'].update(values)
        params['/**/cell_sim']['ros__parameters'].update(
            person_scenario=args.person, scenario_window=args.epochs * args.epoch_period)
    write_text(path, yaml.safe_dump(params, sort_keys=False))
    return path


def assemble(events: list, model: HRCModel, scenario: Scenario, args) -> Trajectory:
    """Per-epoch rows from the watched messages `(topic, value, publication_time)`.

    A message belongs to the last epoch whose signal was published before it. Publication
    times are the writers' source timestamps (one system clock on one host), so this follows
    the causal order (epoch k's signal, then its task state, belief and action, then the cell's
    reaction, then epoch k + 1's signal) whatever order and delay the messages reach this
    observer with: receive times are not used, because an observer that wakes up late takes a
    batch of messages at once. The cell publishes its true state when it reacts to a_k: that
    is the state of epoch k + 1 (its initial one, before the first signal, is epoch 1's). A
    window without joint states has no observation or belief (the row shows O = 0 and no
    belief).
    """
    placed = place_in_epochs([(t, value) for topic, value, t in events if topic == 'hrc/epoch'],
                             [e for e in events if e[0] != 'hrc/epoch'])
    first = {key: values[0][1] for key, values in placed.items()}
    # the last true state seen in epoch k is epoch k + 1's
    true_states = {k + 1: values[-1][1] for (topic, k), values in placed.items()
                   if topic == 'hrc/sim/true_state'}
    missing = [k for k in range(1, args.epochs + 1) if ('hrc/action', k) not in first]
    if missing:
        raise CaseStudyError(f'no action was seen for epochs {missing}')
    rows = []
    for k in range(1, args.epochs + 1):
        true = max((e for e in true_states if e <= k), default=None)
        if true is None or ('hrc/task_state', k) not in first:
            raise CaseStudyError(f'epoch {k}: the cell or the task manager did not report it')
        task = first[('hrc/task_state', k)]
        state = true_states[true][:2] + tuple(int(v) for v in task) + (true_states[true][10],)
        belief = first.get(('hrc/belief', k), np.full(9, np.nan))
        action = first[('hrc/action', k)]
        answer = first.get(('hrc/human_response', k))
        rows.append({
            'epoch': k, **dict(zip(STATE_VARIABLES, state)),
            'O': first.get(('hrc/observation', k), 0),
            **dict(zip(BELIEF_COLUMNS, belief)), 'action': action,
            'accepted': answer if action in ('rh1', 'rh2') else None,
            # dn because the human is in the collision circle or the epoch had no belief
            'fail_safe': action == 'dn' and (state[10] == 0 or ('hrc/belief', k) not in first),
            **{c: float('nan') for c in SCORE_COLUMNS},
            'cost': float(model.cost(np.array([state]), ACTIONS.index(action))[0])})
    # The task records (release, commit, completion) of the same bookkeeping the task manager
    # ran, driven by the observed actions and answers (and, with the arm, the robot's progress
    # published last before the next epoch's signal, the task manager's rule; after the last
    # epoch the last one recorded).
    book = TaskBook(model, initial_task=scenario.initial_state[2:5], schedule=scenario.schedule)
    tasks = TaskEpochs(book, 0, robot_progress=args.robot == 'sim')
    for topic, value, t in events:
        if topic == 'hrc/robot_progress':
            tasks.robot_progress_received(*value, t)
    signals = {value: t for topic, value, t in events if topic == 'hrc/epoch'}
    for row in rows:
        book.begin_epoch(row['epoch'])
        tasks.signal_ns = signals.get(row['epoch'] + 1)
        book.apply(ACTIONS.index(row['action']), bool(row['accepted']), tasks.robot_runs())
    return Trajectory(rows=rows, scenario=scenario, selector=args.selector,
                      mode=args.belief_mode or model.config.belief_mode, seed=args.seed,
                      gamma=model.gamma, tasks=book.records)


def watch(args, out: Path, bag_dir: Path, run: NodeProcesses) -> list:
    """Record and watch the run until the last epoch's action (or the timeout)."""
    import rclpy

    if stop.requested():
        raise Interrupted()
    rclpy.init(**stop.init_options())
    try:
        return _watch(args, out, bag_dir, run)
    finally:
        rclpy.try_shutdown()


def _watch(args, out: Path, bag_dir: Path, run: NodeProcesses) -> list:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    from . import conversions
    from rclpy.event_handler import SubscriptionEventCallbacks

    from .bag import BagWriter, Recorder, message_class
    from .sources import EpochReady

    node = rclpy.create_node('case_study_observer')
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    events: list = []
    decode = {
        'hrc/epoch': conversions.epoch_from_msg,
        'hrc/task_state': lambda m: tuple(conversions.task_state_from_msg(m)[n]
                                          for n in TASK_VARIABLES),
        'hrc/observation': conversions.observation_from_msg,
        'hrc/distance_level': conversions.distance_level_from_msg,
        'hrc/belief': conversions.belief_from_msg,
        'hrc/action': lambda m: ACTIONS[conversions.action_from_msg(m)],
        'hrc/human_response': conversions.human_response_from_msg,
        'hrc/sim/true_state': lambda m: tuple(conversions.true_state_from_msg(m)[n]
                                              for n in STATE_VARIABLES),
        'hrc/robot_progress': lambda m: tuple(conversions.robot_progress_from_msg(m)[n]
                                              for n in ('nature', 'cycles', 'cycles_done')),
    }

    clock = node.get_clock()

    def watcher(topic):
        def on_message(msg, info):
            published = info.get('source_timestamp') if isinstance(info, dict) else None
            try:
                events.append((topic, decode[topic](msg),
                               published or clock.now().nanoseconds))
            except conversions.MessageError as exc:
                node.get_logger().warning(f'{topic}: {exc}', throttle_duration_sec=2.0)
        return on_message

    # Deep reader queues: an observer that wakes up late must still see every message (the
    # latched topics' publishers keep only the last one for late joiners; this reader does
    # not join late).
    latched = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    types = recorded_topics(args)
    # this observer is a listener that must not miss epoch 1: it says when its readers (this
    # one and the bag's) have matched the decision node's clock (hrc/_epoch_ready,
    # min_epoch_ready)
    ready = EpochReady(node)
    for topic in WATCHED + ROBOT_WATCHED * (args.robot == 'sim'):
        subscription = node.create_subscription(
            message_class(types[topic]), topic, watcher(topic),
            latched if topic in LATCHED_TOPICS else reliable,
            event_callbacks=SubscriptionEventCallbacks(matched=ready.update)
            if topic == 'hrc/epoch' else None)
        if topic == 'hrc/epoch':
            ready.readers.append(subscription)
    try:
        with BagWriter(bag_dir) as writer:
            recorder = Recorder(node, recorded_topics(args), writer)
            # the bag's reader of hrc/epoch too (made once the clock is on the graph)
            ready.readers.append(lambda: recorder.subscriptions.get(ready.topic))

            def spin_until(predicate, timeout, what):
                deadline = time.monotonic() + timeout
                while not predicate():
                    if stop.requested():
                        raise Interrupted()
                    if time.monotonic() > deadline:
                        raise CaseStudyError(f'timed out after {timeout:.0f} s waiting for '
                                             f'{what}; node logs are in {out / "logs"}')
                    run.check_alive()
                    executor.spin_once(timeout_sec=0.05)

            def in_graph(names):
                present = {n for n, _ in node.get_node_names_and_namespaces()}
                return all(NODE_NAMES[n] in present for n in names)

            nodes = cell_nodes(args)
            for executable in nodes[:-1]:
                run.start(executable, SIM_MOTION_REMAPS if executable == 'cell_sim_node'
                          and args.input == 'body_tracking' else ())
            spin_until(lambda: in_graph(nodes[:-1]), 30, 'the nodes before the decision node '
                       f'({", ".join(nodes[:-1])}) to appear')
            run.start('decision_node')
            spin_until(lambda: in_graph(nodes), 30, 'the decision node to appear')
            print(f'hrc-case-study: {len(nodes)} nodes up ({", ".join(nodes)}); recording to '
                  f'{bag_dir}', flush=True)
            last = [0]

            def done():
                for topic, value, _ in events[last[0]:]:
                    if topic == 'hrc/epoch':
                        print(f'  epoch {value}', end='', flush=True)
                    elif topic == 'hrc/action':
                        print(f' -> {value}', flush=True)
                last[0] = len(events)
                final = [t for topic, v, t in events if topic == 'hrc/epoch'
                         and v >= args.epochs]
                return bool(final) and any(topic == 'hrc/action' and t > final[0]
                                           for topic, _, t in events)

            spin_until(done, args.timeout, f'{args.epochs} epochs')
            # let the last action's echoes (response, sim state) land in the bag
            end = time.monotonic() + min(0.5, args.epoch_period / 2)
            while time.monotonic() < end and not stop.requested():
                executor.spin_once(timeout_sec=0.05)
            recorder.close()
    finally:
        executor.shutdown(timeout_sec=0)
        node.destroy_node()
    return events


def check_port_free(port: int, host: str = '127.0.0.1') -> None:
    """ToolError when `host:port` cannot be bound now (another HMI, another program): the
    HMI would fail seconds into the run, after the folder and the bag were made. A check,
    not a reservation: the HMI binds it a moment later, as the web server does (address
    reuse on)."""
    with socket.socket() as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, port))
        except OSError as exc:
            raise ToolError(f'--hmi-port {port}: cannot serve the HMI on {host}:{port}: '
                            f'{exc.strerror or exc}; name a free port') from None


def main(argv: list[str] | None = None) -> int:
    with stop.regime():
        return _main(argv)


def _main(argv: list[str] | None) -> int:
    parser = Parser(prog='hrc-case-study', description=__doc__.split('\n')[0])
    parser.add_argument('--out', default='out/case_study', type=path_text, help='output folder')
    parser.add_argument('--epochs', type=bounded_int(1, MAX_RUN_EPOCHS), default=None,
                        help=f'decision epochs (default {case_study().epochs}; with --robot sim '
                             f'{ROBOT_EPOCHS}: the case study\'s tasks at the arm\'s physical '
                             'pace, docs/ROBOT.md 6)')
    parser.add_argument('--epoch-period', type=bounded_float(0.05, 60.0), default=None,
                        help='seconds per decision epoch (default 0.5; with --robot sim 1.0, '
                        "the batch cell's physical epoch)")
    parser.add_argument('--seed', type=bounded_int(0, MAX_SEED), default=0,
                        help="the simulated human's seed")
    parser.add_argument('--selector', default='paper', choices=SELECTORS)
    parser.add_argument('--belief-mode', default='', choices=('',) + BELIEF_MODES,
                        help="'' = the configuration's mode")
    parser.add_argument('--config', default='', help='model configuration (default: shipped)')
    parser.add_argument('--policy', default='', help='policy file (default: shipped)')
    parser.add_argument('--faults', nargs='*', default=[], metavar='KIND:EPOCHS',
                        help='faults the simulated cell injects: dropout, nan_velocity, '
                        'decline, collision, e.g. dropout:5 collision:14-15')
    parser.add_argument('--bag', default='', help='bag folder (default: <out>/bag); it also '
                        'receives the params files of the run, in params/')
    parser.add_argument('--timeout', type=bounded_float(1.0, 86400.0), default=None,
                        help='seconds for the run (default: epochs x epoch period + 60)')
    parser.add_argument('--input', default='joint_states', choices=INPUTS,
                        help="how the human's motion reaches the estimator: joint_states (the "
                        'simulated cell publishes human/*) or body_tracking (through a synthetic '
                        'Azure Kinect stream and body_tracking_node)')
    parser.add_argument('--no-view', dest='view', action='store_false',
                        help='do not start cell_view_node (hrc/markers)')
    parser.add_argument('--hmi', nargs='?', const='show', default='',
                        choices=('show', 'answers'), help='start hmi_node, the web pages: show '
                        "(default) the simulated person's answers, or let a person give the "
                        'answers on the page (the simulated one stops answering)')
    parser.add_argument('--hmi-port', type=bounded_int(1, 65535), default=8080,
                        help="the HMI's port on 127.0.0.1 (default 8080)")
    parser.add_argument('--robot', default='none', choices=ROBOTS,
                        help='sim: the cell with the arm, robot_bridge_node and cobot_sim_node '
                        '(a simulated UR5e under speed and separation monitoring; docs/ROBOT.md)')
    parser.add_argument('--person', default='honest', choices=PERSON_SCENARIOS,
                        help="with --robot sim: who is in the cell, 'honest' (the model's "
                        'person) or a scenario that tests SSM (walk_in, run_in, appear, reach, '
                        'frozen_tracker, lost_tracker; docs/ROBOT.md 4), drawn in the run\'s '
                        'epochs; the run ends with SSM checked against the true bodies')
    args = parser.parse_args(argv)
    if args.person != 'honest' and args.robot != 'sim':
        parser.error('--person needs --robot sim (a person walking at the arm)')
    if args.epoch_period is None:
        args.epoch_period = ROBOT_EPOCH_PERIOD if args.robot == 'sim' else 0.5
    if args.epochs is None:
        args.epochs = ROBOT_EPOCHS if args.robot == 'sim' else case_study().epochs
    if args.timeout is None:
        args.timeout = args.epochs * args.epoch_period + 60.0
    out = Path(args.out)
    bag_dir = Path(args.bag) if args.bag else out / 'bag'
    if args.robot == 'sim' and args.input == 'body_tracking':
        return fail('hrc-case-study', ToolError(SYNTHETIC_TRACKER_WITH_ARM))
    if args.robot == 'sim' and not args.config:   # the arm's model (docs/ROBOT.md, section 4)
        args.config = str(arm_config_path())
    # the inputs first: a refused run makes no folder and leaves the last run's bag alone
    try:
        config = load_config(args.config or default_config_path())
        model = HRCModel(config)
        load_policy(args.policy or default_policy_path(config), config)  # refuse early, clearly
        if args.selector in POMDP_SELECTORS:    # the decision node reads the shipped one
            load_shipped_pomdp_policy(config)
        if args.robot != 'sim':     # the arm's progress (robot_rate) needs the arm
            check_model_cell(model)
        if args.hmi:
            check_port_free(args.hmi_port)
    except (ConfigError, PolicyError, ValueError, ToolError) as exc:
        return fail('hrc-case-study', exc)
    try:
        parse_faults(args.faults)
        if args.bag:            # the user's: never emptied, it must be new or empty
            folder_target(bag_dir, empty=True)
        output_folder(out)
        if not args.bag:        # <out>/bag, the run's own: emptied for the new run
            if bag_dir.is_symlink():
                raise ToolError(f'bag folder {bag_dir} is a symbolic link: the run empties '
                                'its own bag folder, so it must be one; name a bag with --bag')
            folder_target(bag_dir)
    except OSError as exc:
        return fail('hrc-case-study', ToolError(f'bag folder {bag_dir}: {exc.strerror}'))
    except (ValueError, ToolError) as exc:
        return fail('hrc-case-study', exc)
    if not args.bag and bag_dir.is_dir() and any(bag_dir.iterdir()):
        shutil.rmtree(bag_dir)
    shutil.rmtree(out / 'logs', ignore_errors=True)
    (out / SSM_CHECK).unlink(missing_ok=True)     # a run with the arm's; this one may have none
    (out / 'logs').mkdir(parents=True, exist_ok=True)
    shipped = share_dir() / 'config'
    scenario = case_study()
    params = [shipped / 'hrc_params.yaml',
              write_scenario_params(out / 'case_study_params.yaml', scenario)] \
        + [shipped / BODY_TRACKING_SIM_PARAMS] * (args.input == 'body_tracking') \
        + [write_run_params(out / 'run_params.yaml', args)]
    # Single-host run: keep DDS on this host, and let participants announce themselves every
    # 0.1 s (config/fastdds_fast_discovery.xml) so the nodes find each other at once.
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    if not os.environ.get('FASTRTPS_DEFAULT_PROFILES_FILE'):
        os.environ['FASTRTPS_DEFAULT_PROFILES_FILE'] = str(shipped / 'fastdds_fast_discovery.xml')
    if args.hmi:
        print(f'hrc-case-study: the HMI at http://127.0.0.1:{args.hmi_port}/ (operator: '
              f'/operator); ' + ('a person answers the requests there' if args.hmi == 'answers'
                                 else "it shows the simulated person's answers"), flush=True)
    run = NodeProcesses(out / 'logs', params)
    started = time.monotonic()
    try:
        events = watch(args, out, bag_dir, run)
    except (CaseStudyError, NodeProcessError) as exc:
        print(f'\nhrc-case-study: {exc}', file=sys.stderr)
        return 1
    except Interrupted:
        codes = run.stop()
        print(f'\nhrc-case-study: interrupted ({stop.signal_name()}); nodes stopped: '
              + ', '.join(f'{n} exit {c}' for n, c in codes.items()), file=sys.stderr)
        return 130
    finally:
        codes = run.stop()      # again after an interruption: returns the same codes at once
    scenario = Scenario(scenario.initial_state, scenario.schedule, args.epochs,
                        'case study (ROS 2 nodes over DDS)')
    try:
        trajectory = assemble(events, model, scenario, args)
    except CaseStudyError as exc:
        print(f'hrc-case-study: {exc}', file=sys.stderr)
        return 1
    print()
    print(trajectory.table())
    csv_path = trajectory.to_csv(out / 'trajectory.csv')
    plots = plot_trajectory(trajectory, out)
    from .bag import bag_info, format_size
    info = bag_info(bag_dir)
    (bag_dir / 'params').mkdir()
    for i, path in enumerate(params, 1):   # numbered in the order the nodes load them
        shutil.copy(path, bag_dir / 'params' / f'{i}_{path.name}')
    print('\nnodes stopped: ' + ', '.join(f'{n} exit {c}' for n, c in codes.items()))
    for name, code in codes.items():
        if code != 0:       # the run is complete; a node that failed to stop cleanly is a bug
            print(f'hrc-case-study: warning: {name} exited {code} when stopped (SIGINT); see '
                  f'{out / "logs" / (name + ".log")}', file=sys.stderr)
    print(f'wrote {csv_path}')
    for p in plots:
        print(f'wrote {p}')
    bag_file = next(bag_dir.glob('*.mcap'))
    print(f'wrote {bag_file} ({info.message_count} messages, '
          f'{format_size(bag_file.stat().st_size)}); play it with: hrc-bag play {bag_dir}')
    if args.robot == 'sim':
        import json
        from ..core.robot.bridge import load_robot_description
        from ..core.robot.check import format_ssm_check, ssm_check_of_bag
        check = ssm_check_of_bag(bag_dir, load_robot_description())
        print(format_ssm_check(check))
        write_text(out / SSM_CHECK, json.dumps({'person': args.person, **check},
                                               indent=2) + '\n')
        print(f'wrote {out / SSM_CHECK}')
    print(f'node logs in {out / "logs"}; {time.monotonic() - started:.1f} s')
    return 0


if __name__ == '__main__':
    sys.exit(main())
