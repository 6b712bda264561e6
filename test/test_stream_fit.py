"""The task stream counted from recordings (core.learning.stream, hrc-fit --stream)."""

import numpy as np
import pytest

from hrc_ros.core.config import load_config
from hrc_ros.core.learning.recordings import Recording, read_recordings
from hrc_ros.core.learning.stream import fit_stream
from hrc_ros.core.mdp.policy import load_policy
from hrc_ros.core.model import CT, DN, NW, HRCModel
from hrc_ros.core.paths import default_config_path, share_dir
from hrc_ros.core.study.evaluation import BatchSimulator, episodes_of

REPO = share_dir()


def _recording(epochs, tasks, actions, accepted=None):
    n = len(epochs)
    return Recording('hand', '0', np.array(epochs), np.array(tasks, dtype=np.int64),
                     np.full(n, 2), np.full(n, 1), np.array(actions),
                     np.array(accepted if accepted is not None else [-1] * n), np.arange(n))


def test_the_trials_are_counted_as_the_task_step_says():
    """x_k idle and still idle after the step: an idle trial; x_k's task completing: a
    completion trial; a gap in the epochs or a missing action skips the pair."""
    idle = [0] * 8
    robot_task = [1, 1, 0, 0, 0, 0, 0, 0]          # (1, 1, robot only), uncommitted
    committed = [1, 1, 0, 2, 0, 0, 1, 1]           # the robot on it, one epoch left
    new = [2, 2, 1, 0, 0, 0, 0, 0]
    rec = _recording(
        [1, 2, 3, 4, 5, 6, 8, 9, 10],
        [idle, idle, robot_task, committed, new, new, idle, idle, new],
        # 1->2 idle, no arrival; 2->3 idle, arrival (1,1,0); 3->4 ct commits (busy);
        # 4->5 nw completes, (2,2,1) there; 5->6 waits (busy); 6->8 gap; 8->9 dn, none;
        # 9->10 no action recorded (skipped)
        [NW, DN, CT, NW, NW, NW, NW, -1, NW])
    fitted = fit_stream([rec], bootstrap=0)
    assert (fitted.idle_trials, fitted.idle_arrivals) == (3, 1)
    assert (fitted.complete_trials, fitted.complete_arrivals) == (1, 1)
    assert fitted.gaps == 2 and fitted.left_out == 0
    assert fitted.tasks.tolist() == [[1, 1, 0], [2, 2, 1]] and fitted.counts.tolist() == [1, 1]
    section = fitted.section()
    assert section['arrival_idle'] == pytest.approx(1 / 3)
    assert section['q'] == [[1, 1, 0, 0.5], [2, 2, 1, 0.5]]
    # a task the step cannot produce is left out, not counted
    odd = _recording([1, 2], [committed, new], [DN, NW])   # dn: the robot's task stays
    assert fit_stream([odd], bootstrap=0).left_out == 1


def test_the_fit_recovers_the_task_rate_of_the_random_streams():
    """hrc-evaluate's random streams release a task with probability task_rate per epoch, so
    an idle cell gets one with exactly that probability: the interval covers it."""
    config = load_config(default_config_path())
    model = HRCModel(config)
    policy = load_policy(REPO / 'policies' / 'default.npz', config).policy
    for rate in (0.2, 0.5):
        scenarios, seeds = episodes_of(model, 'random', 200, 40, 3, rate)
        run = BatchSimulator(model, policy, mode='posterior').run(scenarios, seeds, 'paper',
                                                                   record=True)
        fitted = fit_stream(run.recordings(model), bootstrap=300, seed=1)
        lo, hi = fitted.intervals['arrival_idle']
        assert lo < rate < hi and hi - lo < 0.2     # seeded: the same draws every run
        assert fitted.idle_trials > 100 and fitted.left_out == 0
        # released tasks queue, so a completion finds the next one more often than rate
        assert fitted.arrival_complete > rate
        assert len(fitted.tasks) == 16


def test_hrc_fit_stream_writes_a_stream_section_from_a_bag(tmp_path):
    from hrc_ros.tools.fit import main
    bag = REPO / 'bags' / 'case_study'
    out = tmp_path / 'fitted.yaml'
    assert main([str(bag), '-o', str(out), '--stream', '--bootstrap', '20', '--starts', '1',
                 '-q']) == 0
    config = load_config(out)
    assert config.has_stream
    recordings = read_recordings([bag], config.rho, config.sigma)
    expected = fit_stream(recordings, bootstrap=0).section()
    assert config.data['stream'] == expected
    # the case study's tasks 2 and 3 are what arrived
    assert sorted(tuple(r[:3]) for r in expected['q']) == [(2, 2, 1), (2, 2, 2)]
    report = (tmp_path / 'fitted.report.json').read_text()
    assert '"stream"' in report and '"arrival_idle"' in report


def test_the_written_q_sums_to_one_without_a_negative_entry_when_a_task_is_rare():
    """q is written to 6 decimals, the rounding's remainder on one entry: on the most frequent
    task, so that a rare one (1 of 1.5 million arrivals) is not pushed below 0 and the fitted
    configuration still validates."""
    from hrc_ros.core.learning.stream import StreamFit
    tasks = np.array([(tp, tc, tx) for tp in (1, 2) for tc in (1, 2) for tx in range(4)])
    fitted = StreamFit(10, 1, 10, 5, tasks, np.array([100_000] * 15 + [1]), 0, 0)
    section = fitted.section()
    assert min(row[3] for row in section['q']) >= 0
    config = load_config(default_config_path(), overrides={'stream': section})
    assert config.stream[3].sum() == pytest.approx(1.0, abs=1e-9)
