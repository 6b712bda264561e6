"""hrc-fit on recordings of the cell with the arm (issue 34, docs/LEARNING.md): read with the
base configuration's rules (its pauses, reach, approach, progress), and the robot's progress
rate counted with intervals (core/learning/rate.py, hrc-fit --rate)."""

import csv

import numpy as np
import pytest

from hrc_ros.core.config import load_config
from hrc_ros.core.learning.fit import prepare
from hrc_ros.core.learning.rate import fit_rate
from hrc_ros.core.learning.recordings import NO_OBSERVATION, UNANSWERED, Recording
from hrc_ros.core.model import ACTIONS, TASK_VARIABLES, HRCModel
from hrc_ros.core.paths import default_config_path, shipped_config_path

COMMITTED = (1, 2, 0, 2, 0, 0, 1, 2)         # a robot-only task, the robot committed, bc = 2


def recording(rows, name='r') -> Recording:
    """rows: (task (8), d, action name) per epoch from 1."""
    epochs = np.arange(1, len(rows) + 1)
    return Recording('test', name, epochs, np.array([r[0] for r in rows], dtype=np.int64),
                     np.array([r[1] for r in rows]), np.full(len(rows), NO_OBSERVATION),
                     np.array([ACTIONS.index(r[2]) for r in rows]),
                     np.full(len(rows), UNANSWERED), epochs)


def with_bc(bc):
    """The committed task with the robot's counter at bc (and the task's tc with it: the robot
    is its only committed agent)."""
    task = list(COMMITTED)
    task[TASK_VARIABLES.index('bc')] = task[TASK_VARIABLES.index('tc')] = bc
    return tuple(task)


def test_the_arms_recordings_are_read_with_the_arms_rules():
    """A retreat that gained nothing from d = 1 reads, with the paper's rules, as the person
    stepping closer (only Delta = +1 fits); with the arm's (retreat_reach 1) as the person
    standing, as it was. A program cycle that SSM slowed (bc stays under nw) cuts the episode
    with the paper's rules and with the arm's deterministic counter, and is one of the two
    outcomes with the arm's progress (a robot_rate in the base, or `counter_may_stay`)."""
    done = (0, 0, 0, 0, 0, 0, 1, 0)      # complete (bp goes to 0 an epoch later, MODEL.md 3.2)
    rows = [(COMMITTED, 1, 'nw'), (COMMITTED, 1, 'nw'), (with_bc(1), 1, 'nw'),
            (done, 1, 'dp'), ((0,) * 8, 1, 'dn')]
    arm = HRCModel(load_config(shipped_config_path('arm'), overrides={
        'model': {'robot_rate': None}}))         # the arm's rules, the paper's counter
    rated = HRCModel(load_config(shipped_config_path('arm'), overrides={
        'model': {'robot_rate': {0: [0.0, 0.1, 0.5, 0.9]}}}))
    paper = prepare([recording(rows)])
    read = prepare([recording(rows)], rated)
    # the move after dp (epoch 4): Delta = -1, 0, +1
    assert paper.move[3].tolist() == [0.0, 0.0, 1.0]
    assert read.move[3].tolist() == [0.0, 1.0, 0.0]
    assert any('does not follow' in issue for issue in paper.issues)
    assert not read.issues and paper.segments > read.segments == 1
    # the arm's rules without its progress: a stayed counter does not follow, as in the
    # paper's model, unless the counter may stay (hrc-fit --rate)
    assert any('does not follow' in issue for issue in prepare([recording(rows)], arm).issues)
    assert not prepare([recording(rows)], arm, counter_may_stay=True).issues
    with pytest.raises(ValueError, match='counter_may_stay needs the model'):
        prepare([recording(rows)], counter_may_stay=True)


def test_the_rate_is_counted_with_intervals_that_cover_the_truth():
    """Working epochs with the counter running at a known rate per band are counted back:
    the estimate within its bootstrap interval, the interval around the truth; a band without
    an epoch keeps the base's value; a successor neither step explains is left out."""
    model = HRCModel(load_config(default_config_path(), overrides={
        'model': {'robot_paused_by': ['dn', 'dp', 'dm']}}))
    truth = {1: 0.1, 3: 0.6}
    rng = np.random.default_rng(8)
    recordings = []
    for e in range(400):
        d = 1 if e % 2 else 3
        ran = rng.random() < truth[d]
        rows = [(COMMITTED, d, 'nw'), (with_bc(1 if ran else 2), d, 'dn')]
        recordings.append(recording(rows, str(e)))
    recordings.append(recording([(COMMITTED, 2, 'nw'), (with_bc(0), 2, 'dn')], 'odd'))
    fitted = fit_rate(recordings, model, bootstrap=300, seed=1)
    assert fitted.trials[0, 1] == fitted.trials[0, 3] == 200 and fitted.left_out == 1
    for d, p in truth.items():
        lo, hi = fitted.intervals[(0, d)]
        assert lo <= fitted.rate[0, d] <= hi and lo < p < hi and hi - lo < 0.2
    assert fitted.rate[0, 2] == 1.0 and (0, 2) not in fitted.intervals    # no trial: base's
    # dn pauses: its epochs are no trials
    paused = fit_rate([recording([(COMMITTED, 1, 'dn'), (COMMITTED, 1, 'dn')])], model)
    assert paused.trials.sum() == 0


def test_hrc_fit_writes_the_rate_into_a_configuration_that_loads(tmp_path, capsys):
    from hrc_ros.tools.fit import main
    rng = np.random.default_rng(2)
    path = tmp_path / 'arm.csv'
    with path.open('w', newline='') as f:
        writer = csv.writer(f)
        writer.writerow(['episode', 'epoch', *TASK_VARIABLES, 'd', 'O', 'action', 'accepted'])
        for e in range(60):
            task, d = COMMITTED, 2
            for k in range(1, 4):
                writer.writerow([e, k, *task, d, int(rng.integers(1, 4)), 'nw', ''])
                bc = task[TASK_VARIABLES.index('bc')]
                if bc == 0 or task[0] == 0:
                    break
                task = with_bc(bc - 1) if rng.random() < 0.4 else task
                if task[TASK_VARIABLES.index('bc')] == 0:
                    task = (0, 0, 0, 0, 0, 0, 0, 0)
    out = tmp_path / 'fitted.yaml'
    argv = [str(path), '-o', str(out), '--base', str(shipped_config_path('arm')), '--rate',
            '--bootstrap', '20', '--starts', '1', '--max-iter', '5', '-q']
    assert main(argv) == 0, capsys.readouterr().err
    printed = capsys.readouterr().out
    assert 'robot_rate (MODEL.md 3.2)' in printed and 'tx 0, d 2:' in printed
    fitted = load_config(out)
    assert fitted.robot_rate[0, 2] == pytest.approx(0.4, abs=0.15)
    base = load_config(shipped_config_path('arm'))
    assert fitted.robot_rate[3, 1] == base.robot_rate[3, 1]   # no epoch at the shared station


def test_a_live_swap_keeps_a_rated_model_rated_and_an_unrated_one_unrated(tmp_path):
    """The decision node's swap rule: a configuration with model.robot_rate (the arm's measured
    progress) where the running one has none, or the other way round, is refused (the cell
    runs with or without the arm by how it started); new rates for a rated cell are taken."""
    import yaml

    from hrc_ros.core.paths import arm_config_path
    from hrc_ros.core.swap import ACCEPTED, check_swap
    from hrc_ros.ros.node_support import load_node_config
    arm = str(arm_config_path())
    data = yaml.safe_load(open(arm))
    unrated, faster = tmp_path / 'unrated.yaml', tmp_path / 'faster.yaml'
    plain = {**data, 'model': {k: v for k, v in data['model'].items() if k != 'robot_rate'}}
    unrated.write_text(yaml.safe_dump(plain))
    rates = {k: [min(1.0, 1.2 * r) for r in v] for k, v in data['model']['robot_rate'].items()}
    faster.write_text(yaml.safe_dump({**data, 'model': {**data['model'], 'robot_rate': rates}}))
    paused = tuple(load_node_config(arm).robot_paused_by)
    assert load_node_config(str(unrated)).robot_rate is None
    out = check_swap(2, 2, arm, str(unrated), paused=paused, rated=True)
    assert out.refused and 'no model.robot_rate' in out.reason \
        and "arm's measured progress" in out.reason and 'restart the nodes' in out.reason
    into = check_swap(2, 2, str(unrated), arm, paused=paused, rated=False)
    assert into.refused and 'unrated.yaml' not in into.reason and 'arm.yaml' in into.reason
    assert check_swap(2, 2, arm, str(faster), paused=paused, rated=True).verdict == ACCEPTED
    # without the check (a node that does not plan), the rate is not the swap's business
    assert check_swap(2, 2, arm, str(unrated), paused=paused).verdict == ACCEPTED
