"""The main job, `hrc-case-study`, as README command 1 runs it (node processes over DDS).

Its trajectory must equal the ROS-free closed loop (`hrc_ros.core.study.simulation.simulate`) for
the
same seed: the nodes run the same core with the same random streams, so any difference is a bug in
the ROS layer (windowing, epoch alignment, conversions). The same run with the human's motion
arriving through a body tracker's stream (`--input body_tracking`: the simulated cell's motion
played as an Azure Kinect stream by tracker_sim_node and read back by body_tracking_node) must
reproduce it epoch by epoch.
"""

import csv
import re
import subprocess
import sys

import numpy as np
import pytest

from hrc_ros.core.config import load_config
from hrc_ros.core.model import STATE_VARIABLES, HRCModel
from hrc_ros.core.paths import default_config_path, shipped_config_path
from hrc_ros.core.mdp.policy import default_policy_path, load_policy
from hrc_ros.core.study.simulation import case_study, simulate
from hrc_ros.ros.bag import bag_info

SEED = 3


def hrc_case_study(out, *options):
    return subprocess.run([sys.executable, '-m', 'hrc_ros.ros.case_study', '--out', str(out),
                           '--seed', str(SEED), '--epoch-period', '0.5', *options],
                          capture_output=True, text=True, timeout=180)


@pytest.fixture(scope='module')
def run(tmp_path_factory, ros_domain_id):
    out = tmp_path_factory.mktemp('case_study')
    return out, hrc_case_study(out)


@pytest.fixture(scope='module')
def body_tracking_run(tmp_path_factory, ros_domain_id):
    out = tmp_path_factory.mktemp('case_study_body_tracking')
    return out, hrc_case_study(out, '--input', 'body_tracking')


def trajectory(out):
    with open(out / 'trajectory.csv') as f:
        return list(csv.DictReader(f))


def assert_same_trajectory(rows, expected_rows):
    """The graph's trajectory.csv rows equal the ROS-free simulation's, epoch by epoch: states,
    observation, action and belief."""
    assert len(rows) == len(expected_rows) == 20
    for got, want in zip(rows, expected_rows):
        k = want['epoch']
        assert int(got['epoch']) == k
        assert [int(got[n]) for n in STATE_VARIABLES] == [want[n] for n in STATE_VARIABLES], k
        assert (int(got['O']), got['action']) == (want['O'], want['action']), k
        np.testing.assert_allclose([float(got[f'b{h}']) for h in range(9)],
                                   [want[f'b{h}'] for h in range(9)], atol=1e-5)


def test_the_main_job_runs_and_says_where_it_wrote(run):
    out, proc = run
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert '5 nodes up (cell_sim_node, task_manager_node, belief_estimator_node, ' \
        'cell_view_node, decision_node)' in proc.stdout
    for name in ('trajectory.csv', 'task_status.png', 'activity.png', 'distance.png',
                 'actions.png', 'belief.png'):
        assert (out / name).stat().st_size > 0
        assert f'wrote {out / name}' in proc.stdout
    assert 'tasks completed 3/3' in proc.stdout
    assert 'cell_sim_node exit 0, task_manager_node exit 0, belief_estimator_node exit 0, ' \
           'cell_view_node exit 0, decision_node exit 0' in proc.stdout
    # epoch 1 came when the graph was ready: the four listeners' readers had matched the clock
    # (hrc/_epoch_ready), not after the graph wait ran out
    assert 'starting the epoch clock after' not in \
        (out / 'logs' / 'decision_node.log').read_text()
    info = bag_info(out / 'bag')
    counts = {t.topic: t.message_count for t in info.topics}
    assert counts['/hrc/action'] == counts['/hrc/epoch'] == 20
    assert counts['/human/joint_states'] > 100
    assert counts['/hrc/markers'] >= 20           # the view: at least one picture an epoch
    assert sorted(p.name for p in (out / 'bag' / 'params').glob('*.yaml')) == \
        ['1_hrc_params.yaml', '2_case_study_params.yaml', '3_run_params.yaml']


def test_the_ros_trajectory_equals_the_ros_free_simulation(run):
    out, proc = run
    assert proc.returncode == 0
    config = load_config(default_config_path())
    expected = simulate(HRCModel(config), load_policy(default_policy_path(), config),
                        case_study(), seed=SEED)
    assert_same_trajectory(trajectory(out), expected.rows)


def test_a_body_tracker_stream_drives_the_suite_to_the_same_decisions(run, body_tracking_run):
    """The same human motion through either input: the same states, observations, beliefs and
    actions in every epoch."""
    out, proc = body_tracking_run
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    stopped = next(line for line in proc.stdout.splitlines() if line.startswith('nodes stopped'))
    failed = re.findall(r'(\w+) exit (-?[1-9]\d*)', stopped)
    assert not failed, stopped + ''.join(
        f'\n--- {name}.log ---\n' + (out / 'logs' / f'{name}.log').read_text()[-3000:]
        for name, _ in failed)
    assert 'tracker_sim_node exit 0, body_tracking_node exit 0' in stopped
    counts = {t.topic: t.message_count for t in bag_info(out / 'bag').topics}
    assert counts['/body_tracking_data'] > 100 and counts['/human/joint_states'] > 100
    assert counts['/hrc/action'] == 20
    direct = trajectory(run[0])
    tracked = trajectory(out)
    assert len(direct) == len(tracked) == 20
    for a, b in zip(direct, tracked):
        k = a['epoch']
        assert [a[n] for n in STATE_VARIABLES] == [b[n] for n in STATE_VARIABLES], k
        assert (a['O'], a['action']) == (b['O'], b['action']), k
        np.testing.assert_allclose([float(b[f'b{h}']) for h in range(9)],
                                   [float(a[f'b{h}']) for h in range(9)], atol=1e-5)


def test_the_posterior_estimator_on_the_graph_equals_the_ros_free_posterior(tmp_path,
                                                                           ros_domain_id):
    """belief_mode posterior: the estimator holds b_k for the task manager's x_k and takes the
    human's answer and the distance move, as the ROS-free loop does with the same seed."""
    proc = hrc_case_study(tmp_path, '--belief-mode', 'posterior', '--no-view')
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    config = load_config(default_config_path())
    model = HRCModel(config)
    policy = load_policy(default_policy_path(), config)
    expected = simulate(model, policy, case_study(), seed=SEED, mode='posterior')
    bayes = simulate(model, policy, case_study(), seed=SEED)
    rows = trajectory(tmp_path)
    assert_same_trajectory(rows, expected.rows)
    # the answers and moves are evidence: the beliefs differ from bayes in some epoch
    gap = max(abs(float(g[f'b{h}']) - b[f'b{h}']) for g, b in zip(rows, bayes.rows)
              for h in range(9))
    assert gap > 1e-3
    assert 'no task state within the hold' not in (tmp_path / 'logs' /
                                                   'belief_estimator_node.log').read_text()


def test_the_suite_runs_a_task_stream_policy_as_the_ros_free_loop_does(tmp_path, ros_domain_id):
    """A configuration with a task stream (MODEL.md 8) and its POMDP policy: the nodes find the
    stream policies by the configuration and decide as the ROS-free loop does."""
    from hrc_ros.core.paths import shipped_config_path
    from hrc_ros.core.pomdp.policy import load_shipped_pomdp_policy
    path = shipped_config_path('case_study_stream')
    proc = hrc_case_study(tmp_path, '--config', str(path), '--selector', 'pomdp',
                          '--belief-mode', 'posterior', '--no-view')
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    config = load_config(path)
    model = HRCModel(config)
    policy = load_policy(default_policy_path(config), config)
    assert policy.path.endswith('case_study_stream.npz')
    expected = simulate(model, policy, case_study(), selector='pomdp', seed=SEED,
                        mode='posterior', pomdp=load_shipped_pomdp_policy(config))
    assert_same_trajectory(trajectory(tmp_path), expected.rows)


def test_a_selector_without_a_shipped_pomdp_policy_is_refused_before_any_node_starts(
        tmp_path, ros_domain_id):
    """pomdp and fib read the shipped POMDP policy of the configuration; for config/paper.yaml
    none is shipped: one line that says what to solve and exit 2 before the nodes start (as
    for a policy file), not a decision node that dies after the graph is up."""
    result = hrc_case_study(tmp_path / 'out', '--config', str(shipped_config_path('paper')),
                            '--selector', 'pomdp', '--epochs', '2')
    assert result.returncode == 2, (result.stdout, result.stderr)
    assert 'nodes up' not in result.stdout
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('hrc-case-study: error:'), lines
    assert '--method pomdp' in lines[0] and 'paper.yaml' in lines[0]
