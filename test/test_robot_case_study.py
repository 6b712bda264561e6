"""The cell with the arm through the ROS graph: `hrc-case-study --robot sim` (docs/ROBOT.md,
"the graph with the arm"), node processes over DDS.

One run of the paper's case study with the bridge and the simulated UR5e, the estimator's d
from the arm's links, the task manager's robot counter from the arm's progress and the 3D
person, as a user runs it: `hrc-case-study --robot sim`, its defaults (seed 0, 40 epochs, the
arm's model config/arm.yaml and its policy). It must complete the case study's three tasks
with every node stopping cleanly, record the robot's topics, never violate SSM while the arm
moves, and agree with the batch cell (`core.robot.cell.ArmCell`) on the same seed: the same
actions, answers, task states and distance levels epoch by epoch; and the arm's path must
stay within the tolerance docs/ROBOT.md states of a batch episode driven by the graph's own
actions (`followed`); the batch runs with the graph's sensing and start (`GRAPH_SETTINGS`).

Agreement, and where it may end (docs/ROBOT.md 6): the arm moves in wall-clock time, so a
program cycle that completes near an epoch's end can be counted one epoch apart in the two
runs, and a distance level read at a boundary near a safety radius can differ; from there they
are two episodes. The runs must agree exactly through at least MIN_AGREE epochs, and where they
part it must be one of those two (the constants' comment). The path is compared with the
episode driven by the graph's actions up to where its task state or answer parts from the
graph's (under the same commands a program cycle can still end an epoch apart).
"""

import csv
import json
import re
import subprocess
import sys

import numpy as np
import pytest

from hrc_ros.core.bagfile import read_bag
from hrc_ros.core.config import load_config
from hrc_ros.core.learning.recordings import place_in_epochs
from hrc_ros.core.mdp.policy import default_policy_path, load_policy
from hrc_ros.core.model import HRCModel, TASK_VARIABLES
from hrc_ros.core.paths import arm_config_path
from hrc_ros.core.robot.bridge import load_robot_description
from hrc_ros.core.robot.cell import GRAPH_SETTINGS, ArmCell
from hrc_ros.core.robot.ssm import MOVING_SPEED, ssm_violated
from hrc_ros.core.study.simulation import Scenario, case_study
from hrc_ros.ros.bag import bag_info, deserialize
from hrc_ros.ros.case_study import ROBOT_EPOCHS

SEED = 0                      # hrc-case-study's defaults with --robot sim
EPOCHS = ROBOT_EPOCHS
# Where the runs may part, and how (test_the_graph_and_the_batch_cell_agree_epoch_by_epoch):
# the graph's arm runs in wall-clock time, each stop and resume a control period or two apart
# from the batch's (more on a loaded machine), so an event that falls within tens of ms of an
# epoch boundary can land in the neighbouring epoch. Two such events: a program cycle's
# completion counted an epoch apart (seed 0's first task ends within tens of ms of the 9/10
# boundary: the graph counts it in 10, the batch in 10 or 11), and a distance level read at a
# boundary where the separation lies within EDGE m of a safety radius (CI with two test
# workers at load 13-16: d 2 against 1 at epoch 7, measured 2026-12-06). And a third, of the
# loaded machine only: an epoch whose window holds no skeleton (CI on 2026-12-07: none in epoch
# 22), where the estimator publishes no d_k and says so, and the decision node holds the last
# d (`epochs_published`), which may be another circle than the batch's. Any other difference,
# or any before MIN_AGREE epochs, fails. 20 epochs agreed on a quiet machine before the
# monitor took the sensors' clock skew as data age.
MIN_AGREE = 4            # the person's first work, the arm's first program, a handover asked
MAX_STARVED = 2          # epochs without a skeleton in the run, at most, for that third way
EDGE = 0.05              # m: 50 ms of a 1 m/s arm or person
# The arm's path (docs/ROBOT.md): the two runs visit the same configurations in the same order,
# PATH_TOLERANCE rad on every joint at most, each run at most PATH_SHIFT s ahead of the other
# (a monotone alignment, path_gap). The graph's arm runs in wall-clock time and each protective
# stop or resume falls a control period or two apart in the two runs (the graph's command
# latency, a loaded machine), so its timing drifts against the batch's by a few tens of ms per
# stop; a fixed-offset comparison failed at 0.19 rad in CI with two test workers at load 8+
# (the same joints, reached 0.2 s later). Measured with the alignment: see the test's message.
PATH_TOLERANCE = 0.1
PATH_SHIFT = 1.0
# ... over the first PATH_EPOCHS epochs at most: a goal planned at an epoch boundary starts from
# where the arm stands then, so once the drift has moved the arm along its path at a boundary
# the two runs' next goals are different lines in joint space (seed 0 with issue 34's bridge:
# the epochs agree through all 40, the paths 0.022 rad through 20 s and 0.12-0.30 rad from 25 s
# on, with a band of 1 or 2 s alike)
PATH_EPOCHS = 20
GRID = 0.02                   # s: both paths resampled on this grid (the batch's control period)
# joint states / separations with the arm moving, so that the SSM checks are not vacuous: 0.2 s
# at 125 Hz. About 360 on a quiet machine, 143 in CI at load 10 and 38 at load 9-13
# (ci_bench --busy 6, 2026-12-07), where stale sensing held the arm more (the safe side)
MOVING_SAMPLES = 25
# per epoch at least: the arm's streams run through every epoch. About 125 a topic on a quiet
# machine (125 Hz, 1 s epochs); at load 9-13 cobot_sim, at a fifth of a core, fell under 10
# in 4 epochs (2026-12-07): its rate on a loaded host is bench/robot_bench.py's to measure
STREAM_PER_EPOCH = 2
# ... and in the median epoch, so that a stream that runs at a small fraction of its rate
# throughout fails: at load about 10 the median was 36 a topic (the least epoch 24; 2026-12-07)
STREAM_MEDIAN = 10


@pytest.fixture(scope='module')
def run(tmp_path_factory, ros_domain_id):
    out = tmp_path_factory.mktemp('case_study_robot')
    proc = subprocess.run([sys.executable, '-m', 'hrc_ros.ros.case_study', '--out', str(out),
                           '--robot', 'sim'],
                          capture_output=True, text=True, timeout=300)
    return out, proc


@pytest.fixture(scope='module')
def batch():
    return batch_episode()


def batch_episode(actions=None):
    """The batch cell's case study on the graph's seed, sensing and start; with `actions`,
    driven by them instead of its own decisions (`ArmCell.episode(actions=)`)."""
    config = load_config(arm_config_path())
    cell = ArmCell(HRCModel(config), load_policy(default_policy_path(config), config),
                   settings=GRAPH_SETTINGS)
    scenario = case_study()
    return cell.episode(Scenario(scenario.initial_state, scenario.schedule, EPOCHS, 'case'),
                        SEED, [SEED, 2], 'paper', record=True, actions=actions)


def messages(out, *topics):
    """(topic, message, publish time ns, header stamp s or None) of the run's bag."""
    rows = []
    for m in read_bag(out / 'bag', topics=list(topics)):
        msg = deserialize(m)
        header = getattr(msg, 'header', None)
        stamp = None if header is None else header.stamp.sec + header.stamp.nanosec * 1e-9
        rows.append((m.topic, msg, m.publish_time_ns, stamp))
    return rows


def test_the_cell_with_the_arm_completes_the_case_study_and_stops_cleanly(run):
    out, proc = run
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert '7 nodes up (cell_sim_node, task_manager_node, belief_estimator_node, ' \
        'cell_view_node, cobot_sim_node, robot_bridge_node, decision_node)' in proc.stdout
    assert 'tasks completed 3/3' in proc.stdout
    stopped = next(line for line in proc.stdout.splitlines() if line.startswith('nodes stopped'))
    assert not re.findall(r'(\w+) exit (-?[1-9]\d*)', stopped), stopped
    assert 'cobot_sim_node exit 0, robot_bridge_node exit 0' in stopped
    counts = {t.topic: t.message_count for t in bag_info(out / 'bag').topics}
    assert counts['/hrc/action'] == counts['/hrc/epoch'] == EPOCHS
    # the bridge's goals, the stop (latched, on change) and the progress; the arm's joint
    # states, the separation and the override (a tick each) stream through every epoch (their
    # rate on a loaded host is cobot_sim's to meet, bench/robot_bench.py)
    # (how many goals is the plan's: with the arm's measured progress it hands the
    # either-agent task to the person, and the arm runs the joint task's program alone)
    assert counts['/joint_trajectory_controller/joint_trajectory'] >= 1
    assert counts['/hrc/protective_stop'] >= 1 and counts['/hrc/robot_progress'] >= 3
    rows = messages(out, '/hrc/epoch', '/joint_states', '/hrc/separation', '/hrc/speed_override',
                    '/human/skeleton')
    signals = [(t, msg.data) for topic, msg, t, _ in rows if topic == '/hrc/epoch']
    placed = place_in_epochs(signals, [(topic, None, t) for topic, _, t, _ in rows
                                       if topic != '/hrc/epoch'])
    for topic in ('/joint_states', '/hrc/separation', '/hrc/speed_override', '/human/skeleton'):
        # the last epoch ends with the run
        per_epoch = [len(placed.get((topic, k), [])) for k in range(1, EPOCHS)]
        # (the person's skeletons, 50 Hz from cell_sim, may miss an epoch or two on a loaded
        # machine: the agreement test's MAX_STARVED)
        if topic != '/human/skeleton':
            assert min(per_epoch) >= STREAM_PER_EPOCH, (topic, per_epoch)
        assert np.median(per_epoch) >= STREAM_MEDIAN, (topic, per_epoch)


def test_ssm_is_never_violated_while_the_arm_moves(run):
    """Every hrc/separation sample of the run: S >= S_p whenever the arm's speed bound is
    above MOVING_SPEED (ISO/TS 15066's formula, checked here from S and the speed, and the
    S_p the simulated arm published)."""
    out, proc = run
    assert proc.returncode == 0
    ssm = load_robot_description().ssm
    samples = np.array([list(msg.data) for _, msg, _, _ in messages(out, '/hrc/separation')])
    moving = samples[samples[:, 8] > MOVING_SPEED]
    # the arm moved for a part of the run (the check is not vacuous; MOVING_SAMPLES)
    assert len(moving) > MOVING_SAMPLES
    assert not np.any(moving[:, 0] < moving[:, 7]), moving[moving[:, 0] < moving[:, 7]][:5]
    assert not any(ssm_violated(s, v, ssm) for s, v in moving[:, [0, 8]])
    assert moving[:, 0].min() > 0.0              # no contact
    # and against the person's true body at each joint state (hrc-case-study's own check of
    # the run, core/robot/check.py, from hrc/sim/true_skeleton in the bag)
    truth = json.loads((out / 'ssm_check.json').read_text())
    assert truth['moving'] > MOVING_SAMPLES and truth['unchecked'] == 0, truth
    assert truth['violations'] == 0, truth


def per_epoch(out):
    """`epochs_published` of the run's bag."""
    rows = messages(out, '/hrc/epoch', '/hrc/distance_level', '/hrc/task_state')
    return epochs_published([(topic, msg.data, t) for topic, msg, t, _ in rows])


def epochs_published(rows):
    """rows (topic, data, publish time ns) -> ({epoch k: (d, task state)}, {k: its signal's
    time}, the epochs whose window holds no d), placed by publication time (the task state's
    eight variables: the arm's model has a queue, whose ninth value, the tasks waiting, the
    batch reads from its own task book). d is d_k the estimator published in epoch k, or,
    where it published none (no skeleton in the window: a tracker starved on a loaded machine,
    CI at 2026-12-07), the last one before, which the decision node's latched input holds."""
    signals = [(t, data) for topic, data, t in rows if topic == '/hrc/epoch']
    placed = place_in_epochs(signals, [(topic, data, t) for topic, data, t in rows
                                       if topic != '/hrc/epoch'])
    published, held, unpublished = {}, None, set()
    for _, k in sorted(signals):
        ds = placed.get(('/hrc/distance_level', k), [])
        if ds:
            d, held = ds[0][1], ds[-1][1]
        else:
            d = held
            unpublished.add(k)
        published[k] = (d, tuple(placed[('/hrc/task_state', k)][0][1])[:8])
    return published, dict((k, t) for t, k in signals), unpublished


def test_an_epoch_without_a_distance_level_holds_the_last_published():
    """A window without d_k (no skeleton) takes the d the decision node held: the last one."""
    ep, d, x = '/hrc/epoch', '/hrc/distance_level', '/hrc/task_state'
    state = list(range(9))
    rows = [(ep, 1, 100), (d, 2, 110), (x, state, 120), (d, 1, 130),
            (ep, 2, 200), (x, state, 220),
            (ep, 3, 300), (d, 0, 310), (x, state, 320)]
    published, signals, unpublished = epochs_published(rows)
    assert published == {1: (2, tuple(state[:8])), 2: (1, tuple(state[:8])),
                          3: (0, tuple(state[:8]))}
    assert signals == {1: 100, 2: 200, 3: 300} and unpublished == {2}
    with pytest.raises(KeyError):               # a task state is never missing
        epochs_published(rows[:-1])


def graph_epochs(out):
    """Per epoch of the graph's run: (action, answer, task state, (d, task state) published)."""
    with open(out / 'trajectory.csv') as f:
        rows = list(csv.DictReader(f))
    published, _, _ = per_epoch(out)
    return [(row['action'], row['accepted'], tuple(int(row[n]) for n in TASK_VARIABLES),
             published[k]) for k, row in enumerate(rows, start=1)]


def batch_epochs(batch):
    return [(a, '' if acc is None else str(int(acc)), x, (d, x))
            for a, acc, x, d in zip(batch.actions, batch.accepted, batch.task_states,
                                    batch.distances)]


def parting_epoch(out, batch) -> int:
    """The first epoch where the graph and the batch differ; EPOCHS + 1 if none."""
    graph, cell = graph_epochs(out), batch_epochs(batch)
    assert len(graph) == len(cell) == EPOCHS
    return next((k for k, (g, b) in enumerate(zip(graph, cell), start=1) if g != b), EPOCHS + 1)


def test_the_graph_and_the_batch_cell_agree_epoch_by_epoch(run, batch):
    out, proc = run
    assert proc.returncode == 0
    graph, cell = graph_epochs(out), batch_epochs(batch)
    k = parting_epoch(out, batch)
    assert k > MIN_AGREE, (k, graph[k - 1], cell[k - 1])
    if k > EPOCHS:
        return
    # where they part: one run's task state is the other's next epoch's (the action and
    # answer then follow each run's own state), or the same task state with d read at a
    # boundary within EDGE of a safety radius
    g, b = [e[2] for e in graph[k - 1:k + 1]], [e[2] for e in cell[k - 1:k + 1]]
    radii = GRAPH_SETTINGS.safety_radii
    edge = min(abs(batch.separations[k - 1] - r) for r in radii)
    shifted = g[0] == b[1] or b[0] == g[1]
    other_d = g[0] == b[0] and graph[k - 1][3][0] != cell[k - 1][3][0]
    borderline = other_d and edge <= EDGE
    # or the graph's estimator published no d_k (no skeleton in the window, its warning on
    # /diagnostics) and the decision node held an older d: the batch's tracker never starves
    _, _, unpublished = per_epoch(out)
    warned = {s.message for _, msg, _, _ in messages(out, '/diagnostics') for s in msg.status
              if s.name.endswith('belief_estimator: epoch')}
    # (a starved epoch or two of a loaded machine, not a stream that stopped: the skeletons'
    # rate through the run is test_the_cell_with_the_arm_completes_...'s to check)
    starved = other_d and k in unpublished and len(unpublished) <= MAX_STARVED and \
        f'epoch {k}: no skeleton since the last epoch; distance level not published' in warned
    assert shifted or borderline or starved, (k, graph[k - 1], cell[k - 1],
                                              f'S {batch.separations[k - 1]:.3f} m',
                                              sorted(unpublished))
    assert batch.tasks_completed == 3


def resample(times, q, grid):
    """q at the times of `grid`, each joint linearly interpolated."""
    return np.stack([np.interp(grid, times, q[:, j]) for j in range(q.shape[1])], axis=1)


def path_gap(a, b, band):
    """The smallest, over monotone alignments of the sampled paths a and b (rows are samples on
    one grid) that pair samples at most `band` grid steps apart, of the largest joint difference
    (rad) between paired samples: a bottleneck dynamic time warping, both starting together and
    either ending up to `band` steps early. Also returns the index of a in the best alignment
    where that largest difference is."""
    n, m = len(a), len(b)
    cost = np.full((n, m), np.inf)
    for i in range(n):
        lo, hi = max(0, i - band), min(m, i + band + 1)
        cost[i, lo:hi] = np.abs(b[lo:hi] - a[i]).max(axis=1)
    best = np.full((n, m), np.inf)
    best[0, 0] = cost[0, 0]
    for i in range(n):
        lo, hi = max(0, i - band), min(m, i + band + 1)
        for j in range(lo, hi):
            if i == 0 and j == 0:
                continue
            before = min(best[i - 1, j] if i else np.inf, best[i, j - 1] if j else np.inf,
                         best[i - 1, j - 1] if i and j else np.inf)
            best[i, j] = max(cost[i, j], before)
    # open end: one run may be up to `band` steps ahead at the compared stretch's end
    ends = [(n - 1, j) for j in range(max(0, m - 1 - band), m)] + \
        [(i, m - 1) for i in range(max(0, n - 1 - band), n - 1)]
    i, j = min(ends, key=lambda e: best[e])
    gap, worst = best[i, j], (cost[i, j], i)
    while i or j:                            # back along the best alignment: where it is worst
        steps = [(i - 1, j - 1), (i - 1, j), (i, j - 1)]
        i, j = min((s for s in steps if min(s) >= 0), key=lambda s: best[s])
        worst = max(worst, (cost[i, j], i))
    return float(gap), int(worst[1])


def test_the_path_gap_takes_a_late_path_and_refuses_another():
    """The alignment forgives a run that stops 0.5 s longer, not one that goes elsewhere or
    too late."""
    grid = np.arange(0.0, 6.0, GRID)
    def path(stop):                          # 0 to 1 rad on two joints, with a stop at 2 s
        t = np.clip(grid - np.clip(grid - 2.0, 0.0, stop), 0.0, None)
        return np.stack([np.clip(t / 4.0, 0.0, 1.0), np.clip(t / 4.0, 0.0, 1.0)], axis=1)
    band = round(PATH_SHIFT / GRID)
    assert path_gap(path(0.0), path(0.5), band)[0] < 0.01
    assert path_gap(path(0.0), path(0.5), round(0.1 / GRID))[0] > PATH_TOLERANCE
    other = path(0.0) * np.array([1.0, -1.0])
    gap, at = path_gap(path(0.0), other, band)
    assert gap > 1.0 and grid[at] > 5.0


@pytest.fixture(scope='module')
def followed(run):
    """The batch cell's episode on the same seed driven by the graph's own actions, epoch by
    epoch (`ArmCell.episode(actions=)`): the arm and the person under the commands the graph
    gave, wherever its decisions parted from the batch's (a distance read at a safety radius
    under load: CI with three test workers, 2026-12-06, d = 0 at 0.896 m in epoch 6, before
    the arm's first motion, which left the decisions' common stretch without motion)."""
    out, proc = run
    assert proc.returncode == 0
    actions = [e[0] for e in graph_epochs(out)]
    assert len(actions) == EPOCHS, actions
    return batch_episode(actions)


def test_the_arm_follows_the_batch_cells_path_within_the_tolerance(run, followed):
    """The graph's joint states (header stamps) against the batch's follower driven by the
    graph's actions, on the batch's clock: a sample at time tau of ROS epoch k (signal at t_k)
    is at (k - 1) + (tau - t_k)."""
    out, proc = run
    assert proc.returncode == 0
    _, signals, _ = per_epoch(out)
    start = {k: t * 1e-9 for k, t in signals.items()}
    ks = sorted(start)
    ros = []
    for _, msg, _, stamp in messages(out, '/joint_states'):
        k = max((k for k in ks if start[k] <= stamp), default=None)
        if k is not None:
            ros.append(((k - 1) + (stamp - start[k]), np.array(msg.position)))
    ros_t = np.array([t for t, _ in ros])
    ros_q = np.array([q for _, q in ros])
    batch_t = np.array([t for t, _ in followed.arm_path])
    batch_q = np.array([q for _, q in followed.arm_path])
    # up to where the task states or answers part (the two are one episode until then; the
    # distance levels may differ at a safety radius, the actions are the same): the graph's
    # arm runs in wall-clock time, each protective stop and resume shifting it by a few tens
    # of ms against the batch (path_gap's alignment takes that), so a program cycle can end an
    # epoch apart
    graph, cell = graph_epochs(out), batch_epochs(followed)
    parting = next((k for k, (g, b) in enumerate(zip(graph, cell), start=1)
                    if g[1:3] != b[1:3]), EPOCHS + 1)         # (the actions are the graph's)
    assert parting > MIN_AGREE, (parting, graph[parting - 1], cell[parting - 1])
    until = min(ros_t.max(), PATH_EPOCHS, parting - 1.0)
    keep = ros_t <= until
    ros_t, ros_q = ros_t[keep], ros_q[keep]
    inside = batch_t <= until
    batch_t, batch_q = batch_t[inside], batch_q[inside]
    moved = np.abs(batch_q - batch_q[0]).max()
    assert moved > 1.0                       # the arm went places: the check is not of a still arm
    grid = np.arange(0.0, until, GRID)
    gap, at = path_gap(resample(ros_t, ros_q, grid), resample(batch_t, batch_q, grid),
                       round(PATH_SHIFT / GRID))
    assert gap <= PATH_TOLERANCE, (f'{gap:.3f} rad', f'near {grid[at]:.2f} s')


def test_the_robot_layout_plots_separation_against_s_p_and_the_override(run):
    """config/foxglove_layout_robot.json: the base layout's panels and the robot's plots, each
    path a field of a topic the run's bag holds."""
    import json

    from hrc_ros.ros.bag import message_class
    from test_view import LAYOUT, layout_topics, mosaic_leaves
    out, proc = run
    assert proc.returncode == 0
    layout = json.loads((LAYOUT.parent / 'foxglove_layout_robot.json').read_text())
    base = json.loads(LAYOUT.read_text())
    panels = layout['configById']
    assert sorted(mosaic_leaves(layout['layout'])) == sorted(panels)
    assert set(base['configById']) < set(panels)
    paths = {p['value'] for c in panels.values() for p in c.get('paths', [])}
    assert {'/hrc/separation.data[0]', '/hrc/separation.data[7]',
            '/hrc/speed_override.data'} <= paths
    recorded = {t.topic: t.type_name for t in bag_info(out / 'bag').topics}
    for topic, fields in layout_topics(layout).items():
        assert topic in recorded, topic
        for field in fields - {''}:
            name, _, index = field.partition('[')
            assert name in message_class(recorded[topic]).get_fields_and_field_types()
    # the separation's layout: 9 values, index 0 S and 7 S_p (conversions.SEPARATION_LABELS)
    from hrc_ros.ros.conversions import SEPARATION_LABELS
    assert (SEPARATION_LABELS[0], SEPARATION_LABELS[7]) == ('S', 'S_p')
    sample = next(msg for _, msg, _, _ in messages(out, '/hrc/separation'))
    assert [(d.label, d.size) for d in sample.layout.dim] == [('separation', 9)]
