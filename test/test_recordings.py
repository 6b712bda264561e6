"""What hrc-fit reads: trajectory CSVs and bags, good and bad (core.learning.recordings,
core.learning.fit.prepare, tools.fit).

- A CSV with a missing column, an unreadable or out-of-range value, an unknown action or
  epochs going backwards is refused in one line naming the file (and line) and what is wrong,
  by the reader and by `hrc-fit` (exit 2, nothing written). The line is the file's own (blank
  lines and quoted multi-line fields counted); a UTF-8 byte order mark changes nothing.
- Rows that contradict the model are reported and left out (an ineligible request accepted),
  and transitions it cannot produce cut the episode (a jump of d, a task state that does not
  follow, a gap in the epochs); an unanswered request takes the answer its successor shows.
- The shipped bags read as the run recorded them: one row per epoch with the recorded action,
  observation, distance and task state, placed by the epoch signals' source timestamps. A bag
  without a needed topic, a damaged bag and a message that cannot be read are handled: a
  message whose CDR bytes do not decode is reported and skipped, the other epochs kept.
- `hrc-fit` end to end on CSVs: a configuration `load_config` accepts, a JSON report, a plot.
  An output that is an input, lies in an input bag, is the base or another output is refused
  before any work; no output folder is made before the inputs are read; a fitted
  configuration that does not validate is one line, and an older OUT.yaml stays as it was.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys

import numpy as np
import pytest

from hrc_ros.core.learning import fit
from hrc_ros.core.config import load_config
from hrc_ros.core.model import ACTIONS, HRCModel
from hrc_ros.core.paths import share_dir
from hrc_ros.core.learning.recordings import RecordingError, read_csv, read_recordings
from hrc_ros.core.study.simulation import Scenario, simulate

BAGS = share_dir() / 'bags'
HEADER = 'episode,epoch,tp,tc,tx,ty,hp,hc,bp,bc,d,O,action,accepted,em,ea'
# a joint task: rh2 accepted at epoch 2, then worked together (d stays 1 under nw only if
# Delta = 0), then the task ends
GOOD = [
    '1,1,1,1,3,0,0,0,0,0,1,1,mh,,2,0',
    '1,2,1,1,3,0,0,0,0,0,1,2,rh2,1,2,0',
    '1,3,1,1,3,3,1,1,1,1,1,2,nw,,2,0',
    '1,4,0,0,0,0,1,0,1,0,1,1,dn,,2,0',
]


def write(tmp_path, rows, header=HEADER, name='run.csv'):
    path = tmp_path / name
    path.write_text('\n'.join([header] + rows) + '\n')
    return path


def test_a_good_csv_reads_as_one_episode_per_episode_value(tmp_path):
    rows = GOOD + [r.replace('1,', '2,', 1) for r in GOOD]
    recordings = read_csv(write(tmp_path, rows), 2, 2)
    assert [r.episode for r in recordings] == ['1', '2']
    r = recordings[0]
    assert r.epoch.tolist() == [1, 2, 3, 4]
    assert [ACTIONS[a] for a in r.action] == ['mh', 'rh2', 'nw', 'dn']
    assert r.accepted.tolist() == [-1, 1, -1, -1] and r.observation.tolist() == [1, 2, 2, 1]
    assert r.task[2].tolist() == [1, 1, 3, 3, 1, 1, 1, 1]
    data = fit.prepare(recordings)
    assert (data.epochs, data.segments, data.issues) == (8, 2, [])
    assert data.answer.tolist() == [0, 1, 0, 0] * 2


def test_without_an_episode_column_the_file_is_one_episode(tmp_path):
    header = HEADER.split(',', 1)[1]
    rows = [r.split(',', 1)[1] for r in GOOD]
    recordings = read_csv(write(tmp_path, rows, header), 2, 2)
    assert len(recordings) == 1 and len(recordings[0]) == 4


@pytest.mark.parametrize('header, rows, message', [
    ('episode,epoch,tp,tc,tx,ty,hp,hc,bp,bc,d,action', GOOD,
     'missing columns O, accepted (a trajectory CSV needs'),
    (HEADER, [GOOD[0].replace(',1,mh', ',7,mh')], ':2: column O = 7 is out of range 1..3'),
    (HEADER, [GOOD[0].replace('1,1,1,1,3', '1,1,5,1,3', 1)], ':2: column tp = 5 is out of range '
     '0..2'),
    (HEADER, [GOOD[0].replace(',mh,', ',jump,')], ":2: column action = 'jump' is not one of"),
    (HEADER, [GOOD[1].replace(',rh2,1,', ',rh2,yes,')], ':2: column accepted must be 1, 0 or '
     "empty, got 'yes'"),
    (HEADER, [GOOD[0].replace('1,1,1,1,3,0,0,0,0,0,1', '1,1,1,1,3,0,0,0,0,0,x')],
     ":2: column d must be an integer in 0..3, got 'x'"),
    (HEADER, [GOOD[1], GOOD[0]], ':3: epochs out of order in episode 1: epoch 1 after epoch 2'),
    (HEADER, [GOOD[0], GOOD[0]], ':3: epochs out of order in episode 1: epoch 1 after epoch 1'),
    (HEADER, [], 'no rows'),
    (HEADER, [GOOD[0] + ',extra'], ':2: the row has 16 columns in the header but not in this'),
])
def test_a_bad_csv_is_refused_in_one_line_naming_the_file(tmp_path, header, rows, message):
    path = write(tmp_path, rows, header)
    with pytest.raises(RecordingError) as error:
        read_csv(path, 2, 2)
    text = str(error.value)
    assert text.startswith(str(path)) and message in text and '\n' not in text


@pytest.mark.parametrize('rows, line', [
    # a blank line, then the bad row on line 4
    ([GOOD[0], '', GOOD[1].replace(',1,2,rh2,', ',1,7,rh2,')], 4),
    # a note quoted over two lines (2-3) and a blank line: the bad row is on line 5
    ([GOOD[0] + ',"a note\nover two lines"', '', GOOD[1].replace(',1,2,rh2,', ',1,7,rh2,')], 5),
    # the bad row itself spans lines 2-3: named by the line it starts on
    ([GOOD[0].replace(',1,mh,', ',7,mh,') + ',"a note\nover two lines"'], 2),
])
def test_an_error_names_the_file_line_the_row_is_on(tmp_path, rows, line):
    path = write(tmp_path, rows, HEADER + ',note')
    with pytest.raises(RecordingError) as error:
        read_csv(path, 2, 2)
    assert str(error.value).startswith(f'{path}:{line}: column O = 7 is out of range')


def test_the_reported_line_of_a_row_left_out_counts_blank_lines(tmp_path):
    rows = ['1,1,1,1,3,0,0,0,0,0,1,1,rh1,1,0,0', '', '', '1,2,1,1,3,0,0,0,0,0,1,1,nw,,0,0']
    path = write(tmp_path, rows)
    data = fit.prepare(read_csv(path, 2, 2))
    assert data.issues == [f'{path}:2: rh1 was accepted, but it was not an eligible request '
                           '(MODEL.md 3.1); row left out']
    assert read_csv(path, 2, 2)[0].line.tolist() == [2, 5]


@pytest.mark.parametrize('header', [HEADER, HEADER.split(',', 1)[1]])
def test_a_csv_saved_with_a_utf8_byte_order_mark_reads_as_without(tmp_path, header):
    """Excel's "CSV UTF-8" starts the file with a byte order mark (and ends lines with CRLF):
    the first column's name is still its name, whether it is episode or epoch."""
    rows = GOOD + [r.replace('1,', '2,', 1) for r in GOOD]
    if header != HEADER:
        rows = [r.split(',', 1)[1] for r in GOOD]
    plain = read_csv(write(tmp_path, rows, header), 2, 2)
    path = tmp_path / 'excel.csv'
    path.write_bytes(b'\xef\xbb\xbf' + '\r\n'.join([header] + rows).encode() + b'\r\n')
    marked = read_csv(path, 2, 2)
    assert [r.episode for r in marked] == [r.episode for r in plain]
    assert len(plain) == (2 if header == HEADER else 1)
    for a, b in zip(marked, plain):
        for name in ('epoch', 'task', 'd', 'observation', 'action', 'accepted', 'line'):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_rows_the_model_cannot_produce_are_reported_and_left_out(tmp_path):
    rows = [
        '1,1,1,1,3,0,0,0,0,0,1,1,rh1,1,0,0',   # rh1 on a joint task: not eligible, "accepted"
        '1,2,1,1,3,0,0,0,0,0,1,1,nw,,0,0',
        '1,3,1,1,3,0,0,0,0,0,3,1,nw,,0,0',     # d from 1 to 3 under nw: no Delta does that
        '1,4,1,1,3,0,0,0,0,0,3,1,ct,,0,0',     # ct cannot start a joint task ...
        '1,5,1,1,3,2,0,0,1,1,3,1,nw,,0,0',     # ... so this task state does not follow
        '1,6,1,1,3,2,0,0,1,1,3,1,nw,,0,0',     # (also: 5 -> 6 does not count bc down)
        '1,8,0,0,0,0,0,0,0,0,3,1,dn,,0,0',     # a gap: epoch 7 is missing
        '1,9,0,0,0,0,0,0,0,0,3,2,dn,,0,0',
    ]
    path = write(tmp_path, rows)
    data = fit.prepare(read_csv(path, 2, 2))
    issues = '\n'.join(data.issues)
    assert f'{path}:2: rh1 was accepted, but it was not an eligible request' in issues
    assert f'{path}:4: d goes from 1 to 3 under nw, which no Delta gives' in issues
    assert f'{path}:6: the task state does not follow from epoch 4 under ct' in issues
    assert f'{path}:7: the task state does not follow from epoch 5 under nw' in issues
    assert f'{path}:8: epoch 8 follows epoch 6: the episode is cut at the gap' in issues
    assert len(data.issues) == 5
    assert data.epochs == 7                                     # row 2 left out
    assert np.diff(data.seg_start).tolist() == [1, 2, 1, 1, 2]  # cut at every bad transition
    assert data.has_move.tolist() == [False, True, False, False, False, True, False]


def test_an_unanswered_request_takes_the_answer_its_successor_shows(tmp_path):
    rows = [GOOD[0], GOOD[1].replace(',rh2,1,', ',rh2,,'), GOOD[2],
            '1,5,1,1,3,0,0,0,0,0,1,2,rh2,,2,0', '1,6,1,1,3,0,0,0,0,0,1,2,nw,,2,0',
            '1,8,1,1,3,0,0,0,0,0,1,2,rh2,,2,0']       # a gap before it, and the last row
    data = fit.prepare(read_csv(write(tmp_path, rows), 2, 2))
    # accepted (the task became joint), refused (the task waits), unknown (no successor)
    assert data.answer.tolist() == [0, 1, 0, 2, 0, 0]


def simulated_csv(tmp_path, model, policy, seeds, epochs=40):
    paths = []
    for seed in seeds:
        scenario = Scenario((seed % 3, 1, 1, 1, 3, 0, 0, 0, 0, 0, 1),
                            tuple((k, (2, 2, k % 4)) for k in range(3, epochs, 4)), epochs)
        trajectory = simulate(model, policy, scenario, seed=seed)
        paths.append(trajectory.to_csv(tmp_path / f'sim{seed}.csv'))
    return paths


def test_hrc_fit_on_csv_writes_a_loadable_configuration_a_report_and_a_plot(tmp_path, policy,
                                                                           default_config):
    model = HRCModel(default_config)
    paths = simulated_csv(tmp_path, model, policy, range(12))
    out = tmp_path / 'out' / 'fitted.yaml'
    result = subprocess.run(
        [sys.executable, '-m', 'hrc_ros.tools.fit', *map(str, paths), '-o', str(out),
         '--bootstrap', '10', '--starts', '2', '--hold', 'emotion.motivate', '--plot'],
        capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    fitted = load_config(out)
    assert fitted.emotion_chain('motivate', 'em').tolist() == \
        default_config.emotion_chain('motivate', 'em').tolist()
    assert fitted.observation_likelihood is not None
    report = json.loads(out.with_suffix('.report.json').read_text())
    assert report['epochs'] == 12 * 40 and report['episodes'] == 12
    assert report['hold'] == ['emotion.motivate.em', 'emotion.motivate.ea']
    assert len(report['parameters']) == 57 and report['bootstrap'] == 10
    held = [p for p in report['parameters'] if p['held']]
    assert len(held) == 6 and all(p['ci95'] is None for p in held)
    assert all(p['ci95'][0] <= p['ci95'][1] for p in report['parameters'] if not p['held'])
    assert report['loglik_trace'] == sorted(report['loglik_trace'])
    assert out.with_suffix('.png').stat().st_size > 10_000
    assert 'p_accept[em=0]' in result.stdout
    # as docs/LEARNING.md says: iteration 0, every 10th and the last, to 4 decimals
    [trace] = [line.split(': ', 1)[1] for line in result.stdout.splitlines()
               if line.startswith('log likelihood by iteration: ')]
    shown = [entry.split(': ') for entry in trace.split(', ')]
    last = len(report['loglik_trace']) - 1
    assert last > 20                           # so that "every 10th" is seen
    assert [int(i) for i, _ in shown] == sorted(set(range(0, last, 10)) | {last})
    assert all(re.fullmatch(r'-\d+\.\d{4}', v) for _, v in shown)
    assert f'next: hrc-solve --config {out}' in result.stdout
    assert sorted(p.name for p in out.parent.iterdir()) == ['fitted.png', 'fitted.report.json',
                                                            'fitted.yaml']   # no temporary


@pytest.mark.parametrize('make, message', [
    (lambda d: (d / 'missing.csv', None), 'missing.csv: cannot read: No such file'),
    (lambda d: (d / 'x.txt', 'hello'), 'x.txt: not a .csv file, a .mcap file or a bag folder'),
    (lambda d: (d / 'bad.csv', 'epoch,tp\n1,0\n'), 'bad.csv: missing columns tc, tx, ty'),
    (lambda d: (d / 'no.mcap', b'not mcap at all'), 'no.mcap'),
])
def test_hrc_fit_refuses_bad_input_in_one_line_before_writing(tmp_path, make, message):
    path, content = make(tmp_path)
    if isinstance(content, str):
        path.write_text(content)
    elif content is not None:
        path.write_bytes(content)
    out = tmp_path / 'fitted.yaml'
    result = subprocess.run([sys.executable, '-m', 'hrc_ros.tools.fit', str(path), '-o',
                             str(out)], capture_output=True, text=True, timeout=120)
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('hrc-fit: error: ') and message in lines[0]
    assert not out.exists()


def test_hrc_fit_refuses_an_unknown_family_to_hold(tmp_path):
    path = write(tmp_path, GOOD)
    result = subprocess.run([sys.executable, '-m', 'hrc_ros.tools.fit', str(path), '-o',
                             str(tmp_path / 'f.yaml'), '--hold', 'p_acept'],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 2 and "unknown parameter family 'p_acept'" in result.stderr


def run_fit(capsys, *argv):
    """hrc-fit in this process, so that a test can break one part of it: (exit status, the
    lines on stderr)."""
    from hrc_ros.tools.fit import main
    status = main([str(a) for a in argv])
    return status, capsys.readouterr().err.strip().splitlines()


QUICK = ('--bootstrap', '0', '--starts', '1', '-q')


def test_hrc_fit_by_the_quasi_newton_em_writes_the_same_outputs(tmp_path, capsys, policy,
                                                                default_config):
    paths = simulated_csv(tmp_path, HRCModel(default_config), policy, range(12))
    out = tmp_path / 'newton.yaml'
    status, lines = run_fit(capsys, *paths, '-o', out, '--method', 'newton', '--bootstrap', 4,
                            '--starts', 1, '-q')
    assert status == 0, lines
    report = json.loads(out.with_suffix('.report.json').read_text())
    assert report['bootstrap'] == 4 and report['converged']
    assert report['loglik_trace'] == sorted(report['loglik_trace'])
    assert all(p['ci95'][0] <= p['ci95'][1] for p in report['parameters'])
    assert load_config(out).observation_likelihood is not None


@pytest.mark.parametrize('outputs, clash', [
    (lambda d: ['-o', d / 'run.csv'], 'output {d}/run.csv (-o) is input {d}/run.csv'),
    (lambda d: ['-o', d / 'link.csv'], 'output {d}/link.csv (-o) is input {d}/run.csv'),
    (lambda d: ['-o', d / 'f.yaml', '--report', d / 'run.csv'],
     'output {d}/run.csv (--report) is input {d}/run.csv'),
    (lambda d: ['-o', d / 'f.yaml', '--plot', d / 'f.yaml'],
     'output {d}/f.yaml (--plot) is also the -o output'),
    (lambda d: ['-o', d / 'f.yaml', '--report', d / 'f.png', '--plot'],
     'output {d}/f.png (--plot) is also the --report output'),
    (lambda d: ['-o', d / 'base.yaml', '--base', d / 'base.yaml'],
     'output {d}/base.yaml (-o) is the base configuration {d}/base.yaml'),
    (lambda d: ['-o', d / 'bag' / 'metadata.yaml'],
     'output {d}/bag/metadata.yaml (-o) is inside input {d}/bag'),
])
def test_hrc_fit_refuses_an_output_that_is_an_input_or_another_output(tmp_path, capsys, outputs,
                                                                      clash):
    path = write(tmp_path, GOOD)
    (tmp_path / 'link.csv').symlink_to(path)
    (tmp_path / 'base.yaml').write_text(share_dir().joinpath('config', 'default.yaml')
                                        .read_text())
    from hrc_ros.core.learning.recordings import BAG_TOPICS
    bag = write_bag(tmp_path / 'bag', BAG_TOPICS, ROWS[:5])     # bag_0.mcap and metadata.yaml

    def files():
        return {p: p.read_bytes() for p in tmp_path.rglob('*') if p.is_file()}
    before = files()
    status, lines = run_fit(capsys, path, bag, *outputs(tmp_path), *QUICK)
    assert status == 2 and len(lines) == 1
    assert lines[0].startswith('hrc-fit: error: ' + clash.format(d=tmp_path))
    assert 'name ' in lines[0]
    assert files() == before                                               # nothing lost


def test_hrc_fit_makes_no_output_folder_before_the_inputs_are_read(tmp_path, capsys):
    status, lines = run_fit(capsys, tmp_path / 'missing.csv', '-o', tmp_path / 'a' / 'f.yaml',
                            '--plot', tmp_path / 'b' / 'f.png', '--report',
                            tmp_path / 'c' / 'f.json')
    assert status == 2 and len(lines) == 1 and 'missing.csv: cannot read' in lines[0]
    assert list(tmp_path.iterdir()) == []


def test_a_fitted_configuration_that_does_not_validate_is_one_line_and_nothing_written(
        tmp_path, capsys, monkeypatch):
    from hrc_ros.core.config import ConfigError

    def refuse(data):
        raise ConfigError('model: p_delta row 0 does not sum to 1')
    monkeypatch.setattr(fit, 'validate', refuse)       # the check fit.fitted_data ends with
    path = write(tmp_path, GOOD)
    status, lines = run_fit(capsys, path, '-o', tmp_path / 'out' / 'f.yaml', *QUICK)
    assert status == 2 and lines == ['hrc-fit: error: the fitted configuration does not '
                                     'validate (model: p_delta row 0 does not sum to 1); '
                                     'nothing written']
    assert list((tmp_path / 'out').iterdir()) == []


def test_a_run_that_writes_an_invalid_configuration_leaves_the_older_one_as_it_was(
        tmp_path, capsys, monkeypatch):
    import hrc_ros.tools.fit as tool
    config_yaml = tool.config_yaml
    monkeypatch.setattr(tool, 'config_yaml',                  # cut short half way
                        lambda *a: config_yaml(*a)[:len(config_yaml(*a)) // 2])
    path = write(tmp_path, GOOD)
    out = tmp_path / 'fitted.yaml'
    out.write_text('# the fit of last week\n')
    status, lines = run_fit(capsys, path, '-o', out, *QUICK)
    assert status == 2
    assert out.read_text() == '# the fit of last week\n'
    assert sorted(p.name for p in tmp_path.iterdir()) == ['fitted.yaml', 'run.csv']
    assert len(lines) == 1
    assert lines[0].startswith('hrc-fit: error: the fitted configuration does not validate')
    assert lines[0].endswith(f'; {out} was not written') and '.tmp' not in lines[0]


# -- bags -------------------------------------------------------------------------------------
def bag_messages(path):
    """(topic, publish time, value) of the hrc topics of a bag, decoded with rclpy."""
    from hrc_ros.core.bagfile import read_bag
    from hrc_ros.ros.bag import deserialize
    out = []
    for m in read_bag(path):
        if m.topic.startswith('/hrc/') and not m.topic.startswith('/hrc/sim'):
            out.append((m.topic, m.publish_time_ns, deserialize(m)))
    return out


@pytest.mark.parametrize('name', ['case_study', 'fault_injection'])
def test_a_shipped_bag_reads_as_its_epochs(name):
    recordings = read_recordings([BAGS / name], 2, 2)
    assert len(recordings) == 1
    r = recordings[0]
    messages = bag_messages(BAGS / name)
    actions = [m.data for topic, _, m in sorted(messages, key=lambda x: x[1])
               if topic == '/hrc/action']
    epochs = [m.data for topic, _, m in sorted(messages, key=lambda x: x[1])
              if topic == '/hrc/epoch']
    assert r.epoch.tolist() == epochs == list(range(1, 21))
    assert [ACTIONS[a] for a in r.action] == actions
    tasks = [list(m.data) for topic, _, m in sorted(messages, key=lambda x: x[1])
             if topic == '/hrc/task_state']
    assert r.task.tolist() == tasks
    observations = [m.data for topic, _, m in sorted(messages, key=lambda x: x[1])
                    if topic == '/hrc/observation']
    assert [o for o in r.observation.tolist() if o] == observations
    answers = [m.data for topic, _, m in messages if topic == '/hrc/human_response']
    assert sorted(r.accepted[r.accepted >= 0].tolist()) == sorted(int(a) for a in answers)


def test_the_fault_injection_bag_collision_is_cut_not_fitted():
    data = fit.prepare(read_recordings([BAGS / 'fault_injection'], 2, 2))
    assert any('d goes from 3 to 0 under dn, which no Delta gives' in m for m in data.issues)
    assert data.segments == 2


def write_bag(path, topics, rows, cut_action=None):
    """A bag of the given hrc topics; rows: (epoch, task, d, O, action, answer or None).
    cut_action: the index of a row whose hrc/action message is written with its CDR bytes cut
    to 6 (inside the string's length field)."""
    from rclpy.serialization import serialize_message
    from std_msgs.msg import Bool, String, UInt8, UInt8MultiArray, UInt32

    from hrc_ros.ros.bag import BagWriter
    types = {'hrc/epoch': 'std_msgs/msg/UInt32', 'hrc/task_state': 'std_msgs/msg/UInt8MultiArray',
             'hrc/distance_level': 'std_msgs/msg/UInt8', 'hrc/observation': 'std_msgs/msg/UInt8',
             'hrc/action': 'std_msgs/msg/String', 'hrc/human_response': 'std_msgs/msg/Bool'}
    t = 1_000_000_000
    with BagWriter(path) as writer:
        for topic in topics:
            writer.add_topic('/' + topic, types[topic])

        def put(topic, message):
            nonlocal t
            t += 1000
            if topic in topics:
                writer.write('/' + topic, message, t, t)

        for i, (epoch, task, d, o, action, answer) in enumerate(rows):
            if epoch == 1:
                t += 10_000_000_000     # a restart: the epoch source was silent for 10 s
            put('hrc/epoch', UInt32(data=epoch))
            put('hrc/task_state', UInt8MultiArray(data=list(task)))
            put('hrc/distance_level', UInt8(data=d))
            if o:
                put('hrc/observation', UInt8(data=o))
            action = String(data=action)
            put('hrc/action', serialize_message(action)[:6] if i == cut_action else action)
            if answer is not None:
                put('hrc/human_response', Bool(data=answer))
    return path


ROWS = [(1, (1, 1, 3, 0, 0, 0, 0, 0), 1, 1, 'mh', None),
        (4000000000, (1, 1, 3, 0, 0, 0, 0, 0), 1, 1, 'mh', None),   # a stray epoch
        (2, (1, 1, 3, 0, 0, 0, 0, 0), 1, 2, 'rh2', True),
        (3, (1, 1, 3, 3, 1, 1, 1, 1), 1, 0, 'nw', None),
        (4, (0, 0, 0, 0, 1, 0, 1, 0), 1, 1, 'dn', None),
        (1, (1, 1, 3, 0, 0, 0, 0, 0), 2, 3, 'rh2', False),     # a restart: episode 2
        (2, (1, 1, 3, 0, 0, 0, 0, 0), 2, 3, 'fly', None)]      # an unreadable action


def test_a_written_bag_reads_with_restarts_as_episodes_and_bad_messages_reported(tmp_path):
    from hrc_ros.core.learning.recordings import BAG_TOPICS, OPTIONAL_BAG_TOPICS
    bag = write_bag(tmp_path / 'bag', BAG_TOPICS + OPTIONAL_BAG_TOPICS, ROWS)
    recordings = read_recordings([bag], 2, 2)
    assert [len(r) for r in recordings] == [4, 1]
    first, second = recordings
    assert any('ignored hrc/epoch 4000000000' in m and 'left out' in m for m in first.issues)
    assert first.accepted.tolist() == [-1, 1, -1, -1]
    assert first.observation.tolist() == [1, 2, 0, 1]
    assert second.accepted.tolist() == [0]
    assert any("a hrc/action message published at" in m and "unknown action 'fly'" in m
               for m in first.issues)
    assert any('epoch 2 has no action; the epoch is left out' in m for m in first.issues)


def test_a_message_whose_bytes_do_not_decode_is_reported_and_the_rest_of_the_bag_read(
        tmp_path):
    from hrc_ros.core.learning.recordings import BAG_TOPICS, OPTIONAL_BAG_TOPICS
    rows = [ROWS[0]] + ROWS[2:5]                   # epochs 1..4 of one episode
    bag = write_bag(tmp_path / 'bag', BAG_TOPICS + OPTIONAL_BAG_TOPICS, rows, cut_action=2)
    [recording] = read_recordings([bag], 2, 2)
    assert recording.epoch.tolist() == [1, 2, 4]   # epoch 3 lost its action, only epoch 3
    assert [ACTIONS[a] for a in recording.action] == ['mh', 'rh2', 'dn']
    assert recording.accepted.tolist() == [-1, 1, -1]
    unread = [m for m in recording.issues if 'a hrc/action message published at' in m]
    assert len(unread) == 1
    assert unread[0].startswith(f'{bag}/bag_0.mcap: ') and 'its 6 CDR bytes do not decode as ' \
        'std_msgs/msg/String' in unread[0] and unread[0].endswith('; left out')
    assert any('epoch 3 has no action; the epoch is left out' in m for m in recording.issues)
    data = fit.prepare([recording])
    assert data.epochs == 3 and unread[0] in data.issues


@pytest.mark.parametrize('leave_out', ['hrc/observation', 'hrc/task_state', 'hrc/epoch'])
def test_a_bag_without_a_needed_topic_is_refused_naming_it(tmp_path, leave_out):
    from hrc_ros.core.learning.recordings import BAG_TOPICS
    topics = tuple(t for t in BAG_TOPICS if t != leave_out)
    bag = write_bag(tmp_path / 'bag', topics, ROWS[:3])
    with pytest.raises(RecordingError) as error:
        read_recordings([bag], 2, 2)
    assert f'has no {leave_out}' in str(error.value) and str(tmp_path) in str(error.value)


def test_a_truncated_bag_is_refused(tmp_path):
    source = next((BAGS / 'case_study').glob('*.mcap'))
    broken = tmp_path / 'broken.mcap'
    broken.write_bytes(source.read_bytes()[:len(source.read_bytes()) // 2])
    with pytest.raises(RecordingError, match='broken.mcap'):
        read_recordings([broken], 2, 2)
