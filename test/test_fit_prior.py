"""hrc-fit --prior: the person prior (observation.prior, MODEL.md 6.1) fitted from recordings.

- Without --prior hrc-fit writes what it wrote before the option existed: the configuration,
  the printed report and the JSON report of a fixed recording (test/data/fit_no_prior, with
  pieces cut at gaps) are the ones the code before --prior wrote: every word the same, every
  number within a unit of its last printed digit (JSON floats within 1e-9 relative), so that
  another CPU's floating-point rounding does not count as a change.
- `prepare` marks the segments that start where a person starts (an episode's first epoch,
  epoch 1) and no other: not pieces cut at a gap or a bad transition, not a recording that
  began mid-run or whose first epoch was left out.
- Without cut pieces the --prior fit is the plain fit (the same model), its prior the plain
  fit's nuisance start.
- A world whose people start from a known non-uniform prior, recorded and fitted by hrc-fit
  --prior: every entry within 4 bootstrap standard deviations of the truth, the truth inside
  at least 8 of the 9 bootstrap 95% intervals, and the estimate far nearer the truth than
  uniform is.
- --prior on recordings none of which starts at epoch 1 is refused in one line.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import re
from pathlib import Path

import numpy as np
import pytest

from hrc_ros.core.config import load_config
from hrc_ros.core.learning import fit
from hrc_ros.core.learning.recordings import Recording
from hrc_ros.core.model import ACTIONS, NW, TASK_VARIABLES, HRCModel
from hrc_ros.core.study.evaluation import BatchSimulator, random_scenarios
from hrc_ros.tools.fit import main

DATA = Path(__file__).parent / 'data' / 'fit_no_prior'
# The people of the recovery test's world: far from uniform, every h possible.
PRIOR = np.array([0.30, 0.04, 0.06, 0.10, 0.20, 0.05, 0.03, 0.07, 0.15])


def write_csv(path: Path, recordings, drop=lambda episode, i: False) -> Path:
    """Recordings as a trajectory CSV (docs/LEARNING.md) with an episode column; rows for
    which drop(episode, i) is true are left out (a gap in the epochs)."""
    with path.open('w', newline='') as f:
        writer = csv.writer(f)
        writer.writerow(['episode', 'epoch', *TASK_VARIABLES, 'd', 'O', 'action', 'accepted'])
        for r in recordings:
            for i in range(len(r)):
                if drop(int(r.episode), i):
                    continue
                accepted = '' if r.accepted[i] < 0 else int(r.accepted[i])
                writer.writerow([r.episode, int(r.epoch[i]), *map(int, r.task[i]), int(r.d[i]),
                                 int(r.observation[i]), ACTIONS[r.action[i]], accepted])
    return path


_NUMBER = re.compile(r'[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?')


def assert_same_text(got: str, want: str) -> None:
    """The same words and layout; each number within one unit of its last printed digit."""
    assert _NUMBER.split(got) == _NUMBER.split(want), 'the words differ'
    for g, w in zip(_NUMBER.findall(got), _NUMBER.findall(want)):
        mantissa = w.lower().split('e')[0]
        digits = len(mantissa.split('.')[1]) if '.' in mantissa else 0
        exponent = int(w.lower().split('e')[1]) if 'e' in w.lower() else 0
        assert abs(float(g) - float(w)) <= 1.0001 * 10.0 ** (exponent - digits), (g, w)


def assert_same_json(got, want, where='report') -> None:
    """The same structure; floats within 1e-9 relative (1e-12 absolute), the rest equal."""
    if isinstance(want, dict):
        assert isinstance(got, dict) and list(got) == list(want), where
        for key in want:
            assert_same_json(got[key], want[key], f'{where}.{key}')
    elif isinstance(want, list):
        assert isinstance(got, list) and len(got) == len(want), where
        for i, (g, w) in enumerate(zip(got, want)):
            assert_same_json(g, w, f'{where}[{i}]')
    elif isinstance(want, float) and not isinstance(got, bool):
        assert got == pytest.approx(want, rel=1e-9, abs=1e-12), where
    else:
        assert got == want, where


def run_fit(*argv) -> tuple[int, str]:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        status = main([str(a) for a in argv])
    return status, out.getvalue()


def test_without_prior_hrc_fit_writes_what_it_wrote_before(tmp_path, monkeypatch):
    """The expected files are the outputs of the code before --prior (commit 4e63add) on
    runs.csv (16 recorded episodes of 40 epochs, every fourth with a gap at epoch 21), less
    what says when and where it ran: the YAML's comment header, the JSON's seconds, paths and
    base. To make them again (only for a deliberate change of the fit's numbers): run this
    fit and write the three parts this test compares. By SQUAREM, the default then (the
    quasi-Newton EM, the default since, takes the resamples further: other numbers)."""
    monkeypatch.chdir(DATA)                # the issues name the input as it was given
    status, stdout = run_fit('runs.csv', '-o', tmp_path / 'fitted.yaml', '--bootstrap', 8,
                             '--starts', 2, '--method', 'squarem')
    assert status == 0
    lines = stdout.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith('parameter'))
    stop = next(i for i, line in enumerate(lines) if line.startswith('wrote '))
    assert_same_text('\n'.join(lines[start:stop]) + '\n', (DATA / 'expected.txt').read_text())
    assert 'initial hidden state (nuisance, not in the configuration)' in stdout
    assert 'the episode is cut at the gap' in stdout           # the data have cut pieces
    body = ''.join(line for line in (tmp_path / 'fitted.yaml').read_text().splitlines(True)
                   if not line.startswith('#'))
    assert_same_text(body, (DATA / 'expected.yaml').read_text())
    assert 'prior' not in body
    report = json.loads((tmp_path / 'fitted.report.json').read_text())
    for volatile in ('seconds', 'inputs', 'output', 'base'):
        report.pop(volatile)
    assert_same_json(report, json.loads((DATA / 'expected.report.json').read_text()))


def _recording(epochs, name='e') -> Recording:
    n = len(epochs)
    return Recording('hand', name, np.array(epochs), np.zeros((n, 8), dtype=np.int64),
                     np.full(n, 2), np.full(n, 1), np.full(n, NW), np.full(n, -1),
                     np.arange(n))


def test_prepare_marks_the_segments_that_start_a_person():
    """Epoch 1 of a recording starts a person; the piece after a gap, a recording from epoch
    4 and one whose epoch 1 was left out (an ineligible request "accepted") do not."""
    dropped = _recording([1, 2, 3], 'first row left out')
    dropped.accepted = np.array([1, -1, -1])          # nw "accepted": the row goes
    data = fit.prepare([_recording([1, 2, 3, 5, 6]), _recording([4, 5, 6], 'late'), dropped])
    assert np.diff(data.seg_start).tolist() == [3, 2, 3, 2]
    assert data.true_starts.tolist() == [True, False, False, False]


@pytest.fixture(scope='module')
def world(default_config, tmp_path_factory):
    """The default configuration with the person prior PRIOR, as a file."""
    import yaml
    data = dict(default_config.data)
    data['observation'] = dict(data['observation'], prior=PRIOR.tolist())
    path = tmp_path_factory.mktemp('world') / 'world.yaml'
    path.write_text(yaml.safe_dump(data))
    return load_config(path)


def recorded(config, policy, episodes, seed):
    """Episodes of 50 epochs of `config`'s world (its people drawn from its prior), recorded
    under `policy` with 20% explored actions."""
    model = HRCModel(config)
    scenarios = random_scenarios(model, episodes, 50, seed=seed,
                                 prior=config.observation_prior)
    run = BatchSimulator(model, policy).run(scenarios, [[seed, e] for e in range(episodes)],
                                            explore=0.2, record=True)
    return run.recordings(model), run.trajectory


def test_random_scenarios_draw_the_people_from_a_prior_and_from_uniform_without(
        default_config):
    model = HRCModel(default_config)
    plain = random_scenarios(model, 2000, 5, seed=3)
    assert plain == random_scenarios(model, 2000, 5, seed=3, prior=None)
    for scenarios, expected in ((plain, np.full(9, 1 / 9)),
                                (random_scenarios(model, 2000, 5, seed=3, prior=PRIOR), PRIOR)):
        h = np.array([3 * s.initial_state[0] + s.initial_state[1] for s in scenarios])
        share = np.bincount(h, minlength=9) / len(h)
        # 2000 draws: each share within 4 binomial standard deviations
        assert np.all(np.abs(share - expected) < 4 * np.sqrt(expected * (1 - expected) / 2000))
    with pytest.raises(ValueError, match='prior must be 9 probabilities'):
        random_scenarios(model, 1, 5, prior=[0.5, 0.5])


def test_without_cut_pieces_the_prior_fit_is_the_plain_fit(world, default_config, policy):
    """Every segment starts an episode at epoch 1: the split start has nothing to split, so
    --prior fits the plain fit's model and its prior is the plain fit's nuisance start (from
    a base without a prior both start from uniform: the same EM steps)."""
    recordings, _ = recorded(world, policy.policy, 60, seed=5)
    data = fit.prepare(recordings)
    assert data.true_starts.all()
    plain = fit.fit(data, default_config, n_init=1, bootstrap=0)
    prior = fit.fit(data, default_config, n_init=1, bootstrap=0, prior=True)
    assert prior.iterations == plain.iterations
    assert prior.prior and not plain.prior
    np.testing.assert_allclose(prior.params.vector(), plain.params.vector(), atol=1e-9)
    np.testing.assert_allclose(prior.params.pi, plain.params.pi, atol=1e-9)
    assert prior.loglik == pytest.approx(plain.loglik, abs=1e-8)


def test_hrc_fit_prior_recovers_the_people_of_a_non_uniform_world(world, policy, tmp_path):
    """400 recorded episodes of a world whose people start from PRIOR, every fourth with a
    gap (a cut piece, which must not be read as a new person), fitted by hrc-fit --prior with
    100 bootstrap resamples."""
    recordings, _ = recorded(world, policy.policy, 400, seed=7)
    path = write_csv(tmp_path / 'runs.csv', recordings,
                     drop=lambda episode, i: episode % 4 == 3 and i == 25)
    out = tmp_path / 'fitted.yaml'
    status, stdout = run_fit(path, '-o', out, '--prior', '--bootstrap', 100, '--starts', 1,
                             '--base', world.source)
    assert status == 0
    fitted = load_config(out)
    estimate = fitted.observation_prior
    assert estimate.sum() == pytest.approx(1.0, abs=1e-12)
    report = json.loads(out.with_suffix('.report.json').read_text())
    rows = [p for p in report['parameters'] if p['family'] == 'observation.prior']
    assert [p['name'] for p in rows] == [f'prior[h={h}]' for h in range(9)]
    assert report['prior_episode_starts'] == 400
    np.testing.assert_allclose([p['fitted'] for p in rows], estimate, atol=1e-6)   # rounded
    low, high = np.array([p['ci95'] for p in rows]).T
    result_sd = (high - low) / (2 * 1.96)              # the interval's width, as a sd
    assert np.all(result_sd > 0)
    assert np.all(np.abs(estimate - PRIOR) < 4 * np.maximum(result_sd, 0.005)), \
        (estimate, PRIOR, low, high)
    assert np.sum((low <= PRIOR) & (PRIOR <= high)) >= 8, (PRIOR, low, high)
    total_variation = 0.5 * np.abs(estimate - PRIOR).sum()
    assert total_variation < 0.1 and total_variation < 0.5 * np.abs(1 / 9 - PRIOR).sum() / 3
    # the report names it as the configuration's, not a nuisance
    assert 'initial hidden state (nuisance' not in stdout
    assert 'observation.prior (the person prior, h = 3*em + ea) from the 400 episode starts' \
        in stdout
    assert 'the 100 pieces cut from episodes or recorded from mid-run start from their own' \
        in stdout
    assert 'prior[h=0]' in stdout and 'observation.prior' in out.read_text().split('\n\n')[0]


def test_hrc_fit_prior_refuses_recordings_where_no_person_starts(tmp_path, default_config,
                                                                 policy, capsys):
    recordings, _ = recorded(default_config, policy.policy, 4, seed=2)
    path = write_csv(tmp_path / 'late.csv', recordings, drop=lambda episode, i: i < 3)
    out = tmp_path / 'fitted.yaml'
    status = main([str(path), '-o', str(out), '--prior', '--bootstrap', '0', '-q'])
    lines = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and len(lines) == 1, lines
    assert lines[0].startswith('hrc-fit: error: --prior: no episode in the recordings starts '
                               'at epoch 1')
    assert not out.exists()
    # the same recordings fit without --prior
    assert main([str(path), '-o', str(out), '--bootstrap', '0', '--starts', '1', '-q']) == 0


def test_the_quasi_newton_em_fits_the_same_prior(world, policy, tmp_path):
    """--method newton moves pi and the cut pieces' pi_cut in its log-ratio coordinates too:
    from the same recordings (with cut pieces) it reaches SQUAREM's maximum."""
    from hrc_ros.core.learning.recordings import read_csv
    recordings, _ = recorded(world, policy.policy, 150, seed=9)
    path = write_csv(tmp_path / 'runs.csv', recordings, drop=lambda episode, i: i == 30)
    data = fit.prepare(read_csv(path, world.rho, world.sigma))
    assert data.segments == 300 and data.true_starts.sum() == 150
    squarem = fit.fit(data, world, n_init=1, bootstrap=0, prior=True)
    newton = fit.fit(data, world, n_init=1, bootstrap=0, prior=True, method=fit.NEWTON)
    assert newton.converged and squarem.converged
    assert newton.loglik >= squarem.loglik - 1e-6 * data.epochs
    np.testing.assert_allclose(newton.params.pi, squarem.params.pi, atol=2e-3)
    np.testing.assert_allclose(newton.params.pi_cut, squarem.params.pi_cut, atol=2e-3)


def test_a_prior_entry_every_resample_keeps_near_zero_is_well_determined():
    """An h no episode starts in: estimate 0, the resamples at 0 but one at 1e-6. Its
    effective support is large (the bootstrap pins it), not 0 (p (1 - p) = 0 at the bound),
    so no 'poorly determined' warning names it; a share the resamples spread is unchanged."""
    samples = np.zeros((200, 2))
    samples[5, 0] = 1e-6
    samples[:, 1] = np.random.default_rng(0).normal(0.5, 0.05, 200)
    estimate = np.array([0.0, 0.5])
    plain = fit.effective_support(estimate, samples)
    bounded = fit.effective_support(estimate, samples, at_bounds=True)
    assert plain[0] == 0.0 and bounded[0] > 1e5
    assert bounded[1] == plain[1] == pytest.approx(0.25 / samples[:, 1].var(ddof=1))
    assert fit._prior_warnings(500, np.r_[bounded[0], np.full(8, 1e6)], 100.0) == []
    assert fit._prior_warnings(500, np.r_[plain[0], np.full(8, 1e6)], 100.0)
