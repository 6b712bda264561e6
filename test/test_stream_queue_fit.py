"""The stream with a queue counted from the tasks waiting (core.learning.stream, MODEL.md 8.1,
hrc-fit --stream on a base with stream.queue; docs/LEARNING.md "The task stream")."""

import json

import numpy as np
import pytest

from hrc_ros.core.config import load_config
from hrc_ros.core.learning.recordings import (TASK_VARIABLES, Recording, read_csv,
                                              read_recordings)
from hrc_ros.core.learning.stream import StreamError, fit_queue_stream, fit_stream
from hrc_ros.core.mdp.policy import load_policy
from hrc_ros.core.model import ACTIONS, CT, NW, HRCModel, step_task
from hrc_ros.core.paths import default_config_path, share_dir
from hrc_ros.core.study.evaluation import BatchSimulator, episodes_of

REPO = share_dir()
QUEUE_CONFIG = REPO / 'config' / 'stream_queue.yaml'


def generated(episodes, epochs, p_idle, p_busy, seed):
    """Recordings of the queue's stream as MODEL.md 8.1 has it, the task step the model's own
    (`step_task`): the robot commits to each task (ct) and works it (nw); a task is released
    with p_busy if the epoch started with a task, else p_idle; the head of the queue enters
    when the step leaves the cell idle. Robot-only tasks (tx = 0), tp and tc drawn in 1..2."""
    rng = np.random.default_rng(seed)
    out = []
    for e in range(episodes):
        x = dict.fromkeys(TASK_VARIABLES, 0)
        queue = []
        rows = []
        for _ in range(epochs):
            action = CT if x['tp'] and x['ty'] == 0 else NW
            rows.append(([x[n] for n in TASK_VARIABLES], action, len(queue)))
            p = p_busy if x['tp'] else p_idle
            if rng.random() < p:
                queue.append((int(rng.integers(1, 3)), int(rng.integers(1, 3)), 0))
            step = step_task({n: np.asarray(v) for n, v in x.items()}, action, False)
            x = {n: int(step[n]) for n in TASK_VARIABLES}
            if x['tp'] == 0 and queue:
                x['tp'], x['tc'], x['tx'] = queue.pop(0)
        n = len(rows)
        epoch = np.arange(1, n + 1)
        out.append(Recording('generated', str(e), epoch, np.array([r[0] for r in rows]),
                             np.full(n, 2), np.full(n, 1), np.array([r[1] for r in rows]),
                             np.full(n, -1), epoch, queued=np.array([r[2] for r in rows])))
    return out


def standard_error(p, n):
    return np.sqrt(p * (1 - p) / n)


@pytest.mark.parametrize('p_idle,p_busy', [(0.3, 0.1), (0.2, 0.2), (0.05, 0.6)])
def test_the_fit_recovers_the_release_probabilities_of_generated_recordings(p_idle, p_busy):
    """The interval covers the truth and the estimate is within 3 standard errors of it
    (seeded: the same draws every run); the 95% percentile interval is about 4 standard errors
    wide, which is what makes 3 a bound and not a tuning."""
    fitted = fit_queue_stream(generated(300, 40, p_idle, p_busy, seed=7), 2, 4.0,
                              bootstrap=500, seed=1)
    assert fitted.left_out == 0 and fitted.gaps == 0
    assert fitted.idle_trials + fitted.busy_trials == 300 * 39
    for name, truth, n in (('arrival_idle', p_idle, fitted.idle_trials),
                           ('arrival_busy', p_busy, fitted.busy_trials)):
        estimate = getattr(fitted, name)
        lo, hi = fitted.intervals[name]
        se = standard_error(truth, n)
        assert n > 1000
        assert lo < truth < hi, (name, lo, truth, hi)
        assert abs(estimate - truth) < 3 * se
        assert 3 * se < hi - lo < 5 * se
    # what entered is q: 4 tasks, equally likely
    assert fitted.tasks.tolist() == [[1, 1, 0], [1, 2, 0], [2, 1, 0], [2, 2, 0]]
    assert np.all(np.abs(fitted.q - 0.25) < 4 * standard_error(0.25, fitted.counts.sum()))
    section = fitted.section()
    assert list(section) == ['queue', 'arrival_idle', 'arrival_busy', 'waiting_cost', 'q']
    assert section['queue'] == 2 and section['waiting_cost'] == 4.0
    config = load_config(QUEUE_CONFIG, overrides={'stream': section})
    assert config.queue == 2 and config.stream[1] == pytest.approx(fitted.arrival_busy, abs=1e-6)


def test_the_releases_are_what_the_queue_count_says_and_two_in_an_epoch_count_as_one():
    idle = [0] * 8
    task = [1, 1, 0, 0, 0, 0, 0, 0]              # uncommitted robot task
    committed = [1, 1, 0, 2, 0, 0, 1, 1]         # the robot on it, one epoch left
    other = [2, 1, 0, 0, 0, 0, 0, 0]
    rows = [  # (x_k, a_k, queued_k)
        (idle, NW, 0),        # 1 -> 2: idle, nothing released
        (idle, NW, 0),        # 2 -> 3: idle, one released and entered at 3
        (task, CT, 0),        # 3 -> 4: busy, two released (queued 0 -> 2): one success, counted
        (committed, NW, 2),   # 4 -> 5: busy, completes, the head enters, queued 2 -> 1: none
        (other, NW, 1),       # 5 -> 6: busy (waits uncommitted), queued 1 -> 1: none
        (other, NW, 1),       # 6 -> 7: queued 1 -> 0 without an entry: left out
        (other, NW, 0),
    ]
    n = len(rows)
    epoch = np.arange(1, n + 1)
    rec = Recording('hand', '0', epoch, np.array([r[0] for r in rows]), np.full(n, 2),
                    np.full(n, 1), np.array([r[1] for r in rows]), np.full(n, -1), epoch,
                    queued=np.array([r[2] for r in rows]))
    fitted = fit_queue_stream([rec], 2, 4.0, bootstrap=0)
    assert (fitted.idle_trials, fitted.idle_releases) == (2, 1)
    assert (fitted.busy_trials, fitted.busy_releases) == (3, 1)
    assert (fitted.multiple, fitted.multiple_tasks) == (1, 2)
    assert fitted.left_out == 1 and fitted.gaps == 0
    assert fitted.tasks.tolist() == [[1, 1, 0], [2, 1, 0]]
    assert any('1 epoch(s) released two or more tasks (2 in all)' in w
               for w in fitted.warnings())
    # an unknown count (-1) at either end skips the pair
    rec.queued[4] = -1
    skipped = fit_queue_stream([rec], 2, 4.0, bootstrap=0)
    assert skipped.gaps == 2 and skipped.busy_trials == 1 and skipped.left_out == 1


def test_the_random_streams_of_hrc_evaluate_recorded_with_the_queue_give_back_their_rate():
    """config/stream_queue.yaml's truth: a release with probability 0.2 per epoch whatever the
    cell does (the first task, at epoch 1, is the episode's start, no trial)."""
    config = load_config(QUEUE_CONFIG)
    model = HRCModel(config)
    policy = load_policy(REPO / 'policies' / 'stream_queue.npz', config).policy
    scenarios, seeds = episodes_of(model, 'random', 200, 40, 3, 0.2)
    run = BatchSimulator(model, policy, mode='posterior').run(scenarios, seeds, 'paper',
                                                               record=True)
    recordings = run.recordings(model)
    assert all(r.queued is not None for r in recordings)
    fitted = fit_queue_stream(recordings, config.queue, config.waiting_cost, bootstrap=300,
                              seed=1)
    assert fitted.left_out == 0 and fitted.multiple == 0
    assert fitted.idle_trials + fitted.busy_trials == 200 * 39
    # what was released: the schedules' tasks from epoch 2 on
    released = sum(sum(1 for k, _ in s.schedule if 2 <= k <= 40) for s in scenarios)
    assert fitted.idle_releases + fitted.busy_releases == released
    for name in ('arrival_idle', 'arrival_busy'):
        lo, hi = fitted.intervals[name]
        assert lo < 0.2 < hi and hi - lo < 0.05


def write_csv(path, recordings, queued=True):
    header = ['episode', 'epoch', *TASK_VARIABLES, 'd', 'O', 'action', 'accepted']
    lines = [','.join(header + (['queued'] if queued else []))]
    for rec in recordings:
        for i in range(len(rec)):
            accepted = '' if rec.accepted[i] < 0 else str(rec.accepted[i])
            row = [rec.episode, str(rec.epoch[i]), *map(str, rec.task[i]), str(rec.d[i]),
                   str(rec.observation[i]), ACTIONS[rec.action[i]], accepted]
            if queued:
                row.append('' if rec.queued[i] < 0 else str(rec.queued[i]))
            lines.append(','.join(row))
    path.write_text('\n'.join(lines) + '\n')
    return path


def test_queued_round_trips_through_a_csv(tmp_path):
    recordings = generated(3, 12, 0.3, 0.3, seed=2)
    recordings[1].queued[4] = -1                      # an empty cell: unknown
    back = read_csv(write_csv(tmp_path / 'q.csv', recordings), 2, 2)
    assert [r.queued.tolist() for r in back] == [r.queued.tolist() for r in recordings]
    assert back[1].queued[4] == -1
    assert all(r.queued is None
               for r in read_csv(write_csv(tmp_path / 'n.csv', recordings, False), 2, 2))
    bad = tmp_path / 'bad.csv'
    bad.write_text((tmp_path / 'q.csv').read_text().replace(',0\n', ',x\n', 1))
    from hrc_ros.core.learning.recordings import RecordingError
    with pytest.raises(RecordingError, match='column queued must be an integer'):
        read_csv(bad, 2, 2)


def test_queued_round_trips_through_a_bag(tmp_path):
    from test_recordings import write_bag

    from hrc_ros.core.learning.recordings import BAG_TOPICS
    eight = [(1, (1, 1, 3, 0, 0, 0, 0, 0), 1, 1, 'ct', None),
             (2, (1, 1, 3, 2, 0, 0, 1, 1), 1, 2, 'nw', None),
             (3, (0, 0, 0, 0, 0, 0, 0, 0), 1, 1, 'nw', None)]
    nine = [(k, task + (q,), d, o, a, r) for (k, task, d, o, a, r), q in
            zip(eight, (0, 3, 255))]
    rec, = read_recordings([write_bag(tmp_path / 'nine', BAG_TOPICS, nine)], 2, 2)
    assert rec.queued.tolist() == [0, 3, 255]
    assert rec.task.tolist() == [list(r[1]) for r in eight]
    old, = read_recordings([write_bag(tmp_path / 'eight', BAG_TOPICS, eight)], 2, 2)
    assert old.queued is None and old.task.tolist() == rec.task.tolist()
    # 255 is the ROS cap ("255 or more"): a pair that touches it is skipped, not counted
    fitted = fit_queue_stream([rec], 2, 4.0, bootstrap=0)
    assert fitted.gaps == 1 and fitted.busy_trials == 1 and fitted.busy_releases == 1


def run_fit(capsys, *args):
    from hrc_ros.tools.fit import main
    status = main([str(a) for a in args])
    return status, capsys.readouterr()


def test_hrc_fit_stream_on_a_queue_base_writes_the_fitted_queue_stream(tmp_path, capsys):
    recordings = generated(40, 25, 0.3, 0.1, seed=5)
    csv = write_csv(tmp_path / 'runs.csv', recordings)
    out = tmp_path / 'fitted.yaml'
    status, printed = run_fit(capsys, csv, '-o', out, '--base', QUEUE_CONFIG, '--stream',
                              '--bootstrap', '50', '--starts', '1', '-q')
    assert status == 0, printed.err
    config = load_config(out)
    expected = fit_queue_stream(read_csv(csv, 2, 2), 2, 4.0, bootstrap=0).section()
    assert config.data['stream'] == expected
    assert config.queue == 2 and config.waiting_cost == 4.0      # the base's, not fitted
    assert 'not fitted' in out.read_text().split('\n\n')[0]
    report = json.loads((tmp_path / 'fitted.report.json').read_text())['stream']
    assert report['idle_trials'] + report['busy_trials'] == 40 * 24
    assert set(report['intervals']) >= {'arrival_idle', 'arrival_busy'}
    assert 'arrival_busy' in printed.out


def test_hrc_fit_stream_on_a_queue_base_refuses_recordings_without_queued(tmp_path, capsys):
    csv = write_csv(tmp_path / 'runs.csv', generated(5, 10, 0.3, 0.3, seed=1), queued=False)
    out = tmp_path / 'fitted.yaml'
    status, printed = run_fit(capsys, csv, '-o', out, '--base', QUEUE_CONFIG, '--stream', '-q')
    lines = printed.err.strip().split('\n')
    assert status == 2 and len(lines) == 1 and not out.exists()
    assert lines[0].startswith(f'hrc-fit: error: {csv} episode 0 has no queued')
    assert 'stream.queue' in lines[0] and 'queued column' in lines[0]
    with pytest.raises(StreamError, match='has no queued'):
        fit_queue_stream(read_csv(csv, 2, 2), 2, 4.0)
    # without --stream the same recordings fit (the queue is not asked for)
    assert run_fit(capsys, csv, '-o', out, '--base', QUEUE_CONFIG, '--bootstrap', '0',
                   '--starts', '1', '-q')[0] == 0


def test_a_queue_less_fit_ignores_queued_byte_for_byte(tmp_path, capsys):
    """The stream of MODEL.md 8 is counted as before: the same rows with and without a queued
    column give the same configuration and the same report, byte for byte (but the header's
    time and inputs)."""
    recordings = generated(30, 20, 0.3, 0.3, seed=3)
    texts, reports = [], []
    for queued in (True, False):
        folder = tmp_path / str(queued)
        folder.mkdir()
        csv = write_csv(folder / 'runs.csv', recordings, queued)
        out = folder / 'fitted.yaml'
        status, printed = run_fit(capsys, csv, '-o', out, '--stream', '--bootstrap', '30',
                                  '--starts', '1', '-q')
        assert status == 0, printed.err
        texts.append(out.read_text().split('\n\n', 1)[1])
        report = json.loads((folder / 'fitted.report.json').read_text())
        reports.append(json.dumps({k: v for k, v in report.items()
                                   if k not in ('inputs', 'output', 'seconds')}))
        assert load_config(out).data['stream'] == fit_stream(
            read_csv(csv, 2, 2), bootstrap=0).section()
        assert 'arrival_complete' in load_config(out).data['stream']
    assert texts[0] == texts[1] and reports[0] == reports[1]


def test_the_default_base_still_fits_the_queue_less_stream_from_queue_recordings():
    """A queue-less base counts arrivals as MODEL.md 8 does, whatever queued says."""
    recordings = generated(20, 20, 0.3, 0.3, seed=4)
    stripped = [Recording(r.source, r.episode, r.epoch, r.task, r.d, r.observation, r.action,
                          r.accepted, r.line) for r in recordings]
    a, b = fit_stream(recordings, bootstrap=50), fit_stream(stripped, bootstrap=50)
    assert a.report() == b.report() and a.section() == b.section()
    assert load_config(default_config_path()).queue is None


def test_a_bag_the_node_suite_records_with_a_queue_fits_the_queue_stream(tmp_path,
                                                                          ros_domain_id):
    """The whole path on the ROS graph: hrc-case-study runs the nodes with
    config/stream_queue.yaml and records a bag; its task states carry the ninth value, and
    hrc-fit --stream on that base counts the case study's two scheduled releases (tasks 2 and
    3, after epoch 1's) from it."""
    import subprocess
    import sys
    from pathlib import Path
    script = Path(sys.executable).parent / 'hrc-case-study'
    result = subprocess.run(
        [str(script), '--out', str(tmp_path / 'run'), '--config', str(QUEUE_CONFIG),
         '--policy', str(REPO / 'policies' / 'stream_queue.npz'), '--epochs', '24',
         '--epoch-period', '0.25', '--seed', '3', '--no-view'],
        capture_output=True, text=True, timeout=240)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr
    bag = tmp_path / 'run' / 'bag'
    rec, = read_recordings([bag], 2, 2)
    assert rec.queued is not None and len(rec) == 24 and (rec.queued >= 0).all()
    out = tmp_path / 'fitted.yaml'
    from hrc_ros.tools.fit import main
    assert main([str(bag), '-o', str(out), '--base', str(QUEUE_CONFIG), '--stream',
                 '--bootstrap', '20', '--starts', '1', '-q']) == 0
    report = json.loads((tmp_path / 'fitted.report.json').read_text())['stream']
    assert report['idle_trials'] + report['busy_trials'] == 23 and report['left_out'] == 0
    assert report['idle_releases'] + report['busy_releases'] == 2
    assert sorted(tuple(r[:3]) for r in load_config(out).data['stream']['q']) == [
        (2, 2, 1), (2, 2, 2)]
