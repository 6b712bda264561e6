"""The plant's fit.prior and fit.stream (hrc-fleet, docs/FLEET.md): hrc-fit's --prior and
--stream in a cell's fit, run through the cell's pipeline (its read, fit, bootstrap and summary
jobs, serially, without Ray) on recordings written as a CSV:

- fit.prior: the fitted YAML's observation.prior is the one `fit.fit(..., prior=True)` gives
  on the same data (and none without it); the plant's fanned-out bootstrap gives the prior's
  interval and effective support exactly as fit's own bootstrap does from the same resamples.
- fit.stream: the fitted YAML is the one hrc-fit --stream writes for the same recording files
  (the stream section, and the rest of the configuration too); a base with stream.queue and
  recordings without the tasks waiting fail the cell with hrc-fit's message.
- the promotion check's refits fit the same model: each refit's configuration is the fit of
  its resampled episodes, its own prior included, with the cell's stream as counted.
"""

from __future__ import annotations

import json
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
import yaml

from hrc_ros.core.config import load_config
from hrc_ros.core.learning import fit as fitting
from hrc_ros.core.learning.recordings import read_recordings
from hrc_ros.core.paths import shipped_config_path
from hrc_ros.core.plant import stages
from hrc_ros.core.plant.pipeline import CellPipeline, Ref, resolve, run_stage
from hrc_ros.core.plant.spec import load_plant


@pytest.fixture(scope='module')
def recordings_csv(default_config, tmp_path_factory):
    """8 episodes x 50 epochs of the shipped policy (20% explored), each from epoch 1."""
    from hrc_ros.core.mdp.policy import default_policy_path, load_policy
    from hrc_ros.core.model import HRCModel
    from hrc_ros.core.study.evaluation import BatchSimulator, episodes_of
    model = HRCModel(default_config)
    policy = load_policy(default_policy_path(default_config), default_config)
    scenarios, seeds = episodes_of(model, 'random', 8, 50, 4)
    result = BatchSimulator(model, policy).run(scenarios, seeds, 'paper', explore=0.2,
                                               record=True)
    path = tmp_path_factory.mktemp('plant_fit') / 'line.csv'
    path.write_text(stages.recordings_csv(result.recordings(model)))
    return path


def cell(tmp_path, recordings, fit: str, base: str = 'default'):
    plant = tmp_path / 'plant.yaml'
    plant.write_text(f'cells:\n  - name: a\n    recordings: {recordings}\n    base: {base}\n'
                     f'    run: always\n    fit: {fit}\n')
    return load_plant(plant).cells[0]


def fitted(spec, base):
    """The cell's pipeline run as far as its fit summary: its own read, fit, bootstrap and
    summary jobs with the payloads they name (the drift test left out) ->
    (the summary's facts, its payload, the read payload)."""
    p = CellPipeline(spec, '/nonexistent/out', rho=base.rho, sigma=base.sigma)
    payloads = {'@base:a': base}
    jobs = p.start()
    facts = {}
    while jobs:
        job = jobs.pop(0)
        if job.key.startswith(('drift', 'null')):
            continue
        facts, payload = run_stage(job.stage, *resolve(job.args, payloads, 'a'))
        assert 'error' not in facts, facts
        payloads[('a', job.key)] = payload
        if job.key == 'summary':
            return facts, payload, payloads[('a', 'read')]
        jobs += p.done(job.key, facts)
    raise AssertionError(f'no summary: {p.entry["reason"]}')


def direct_fit(path, base, settings, prior):
    data = fitting.prepare(read_recordings([path], base.rho, base.sigma))
    return fitting.fit(data, base, settings['hold'], n_init=settings['starts'], seed=0,
                       tol=settings['tol'], max_iter=settings['max_iter'], bootstrap=0,
                       prior=prior)


def test_fit_prior_writes_the_prior_fit_gives_and_its_bootstrap_interval(
        tmp_path, recordings_csv, default_config):
    spec = cell(tmp_path, recordings_csv, '{prior: true, bootstrap: 10, starts: 1}')
    facts, summary, _ = fitted(spec, default_config)
    want = direct_fit(recordings_csv, default_config, spec.fit, prior=True)
    np.testing.assert_allclose(summary['result'].params.pi, want.params.pi, rtol=0, atol=1e-9)
    written = yaml.safe_load(summary['yaml'])['observation']['prior']
    np.testing.assert_allclose(written,
                               fitting.fitted_data(want, default_config)['observation']['prior'],
                               rtol=0, atol=1e-9)
    assert 'observation.prior' in summary['yaml'].split('\n\n')[0]       # the header says so
    # the bootstrap's 10 resamples carry their priors: the interval is theirs, by fit's rules
    result = summary['result']
    assert facts['bootstrap'] == 10 and result.prior_samples.shape == (10, 9)
    np.testing.assert_array_equal(result.prior_interval,
                                  np.percentile(result.prior_samples, [2.5, 97.5], axis=0))
    report = fitting.report_dict(result)
    prior_rows = [p for p in report['parameters'] if p['family'] == 'observation.prior']
    assert len(prior_rows) == 9 and all(p['ci95'] is not None for p in prior_rows)


def test_without_fit_prior_the_fitted_yaml_has_the_bases_prior(tmp_path, recordings_csv,
                                                             default_config):
    spec = cell(tmp_path, recordings_csv, '{bootstrap: 0, starts: 1}')
    assert spec.fit['prior'] is False and spec.fit['stream'] is False
    _, summary, data = fitted(spec, default_config)
    assert default_config.observation_prior is None
    assert 'prior' not in yaml.safe_load(summary['yaml'])['observation']
    assert 'stream' not in yaml.safe_load(summary['yaml'])
    assert 'recordings' not in data and summary['stream'] is None    # nothing kept for it


def test_with_bootstrap_gives_the_prior_interval_fit_gives_from_the_same_resamples(
        recordings_csv, default_config):
    data = fitting.prepare(read_recordings([recordings_csv], 2, 2))
    whole = fitting.fit(data, default_config, n_init=1, bootstrap=6, max_iter=200, prior=True)
    point = replace(whole, interval=None, samples=None, effective=None, prior_interval=None,
                    prior_samples=None, prior_effective=None,
                    warnings=fitting.fit(data, default_config, n_init=1, bootstrap=0,
                                         max_iter=200, prior=True).warnings)
    again = fitting.with_bootstrap(point, whole.samples, whole.prior_samples)
    np.testing.assert_array_equal(again.prior_interval, whole.prior_interval)
    np.testing.assert_array_equal(again.prior_effective, whole.prior_effective)
    np.testing.assert_array_equal(again.interval, whole.interval)
    assert again.warnings == whole.warnings


def test_fit_stream_writes_what_hrc_fit_stream_writes(tmp_path, recordings_csv,
                                                      default_config, capsys):
    from hrc_ros.tools.fit import main
    spec = cell(tmp_path, recordings_csv, '{stream: true, bootstrap: 0, starts: 1}')
    facts, summary, data = fitted(spec, default_config)
    out = tmp_path / 'hrc_fit.yaml'
    assert main([str(recordings_csv), '-o', str(out), '--stream', '--bootstrap', '0',
                 '--starts', '1', '--seed', '0', '--tol', str(spec.fit['tol']),
                 '--max-iter', str(spec.fit['max_iter']), '-q']) == 0
    want = yaml.safe_load(out.read_text())
    got = yaml.safe_load(summary['yaml'])
    assert 'stream' in got and got['stream'] == want['stream']
    assert got == want                                     # the rest of the fit is the same
    assert facts['stream']['section'] == want['stream']
    # hrc-fit's report has the stream's; so has the plant's fitted.report.json (same seed)
    files = stages.outputs({'cell': 'a'}, summary, None, None, None)[1]
    report = json.loads(files['fitted.report.json'])
    assert report['stream'] == json.loads(out.with_suffix('.report.json').read_text())['stream']
    assert len(data['recordings']) == 8                    # kept for the stream


def test_fit_stream_on_a_queue_base_without_queued_fails_the_cell_as_hrc_fit_refuses(
        tmp_path, recordings_csv, capsys):
    from hrc_ros.tools.fit import main
    base_path = shipped_config_path('stream_queue')
    lines = recordings_csv.read_text().splitlines()    # the same epochs without `queued`
    assert lines[0].endswith(',queued')
    recordings_csv = tmp_path / 'no_queued.csv'
    recordings_csv.write_text(''.join(line.rsplit(',', 1)[0] + '\n' for line in lines))
    spec = cell(tmp_path, recordings_csv, '{stream: true}', base=str(base_path))
    base = load_config(base_path)
    p = CellPipeline(spec, '/nonexistent/out', rho=base.rho, sigma=base.sigma)
    job = p.start()[0]
    assert job.key == 'read' and job.args[-2:] == (Ref('@base:a'), False)
    facts, _ = run_stage(job.stage, *resolve(job.args, {'@base:a': base}, 'a'))
    capsys.readouterr()
    assert main([str(recordings_csv), '-o', str(tmp_path / 'x.yaml'), '--stream', '--base',
                 str(base_path), '-q']) != 0
    message = capsys.readouterr().err.strip().removeprefix('hrc-fit: error: ')
    assert 'has no queued' in message and '\n' not in facts['error']
    assert facts['error'] == f'fit.stream: {message}'


def test_a_refit_fits_its_resample_as_the_cell_is_fitted_with_the_cells_stream(
        tmp_path, recordings_csv, default_config, monkeypatch):
    """A refit of the promotion check (stages.refit): the fit of its resampled episodes from
    the base with the cell's settings, its own person prior among them, and the stream the
    cell's fit counted (the refits refit what EM fits)."""
    spec = cell(tmp_path, recordings_csv, '{prior: true, stream: true, starts: 1, bootstrap: 0}')
    _, summary, data = fitted(spec, default_config)
    point = summary['result']
    monkeypatch.setattr('hrc_ros.core.mdp.solver.value_iteration',
                        lambda model, start=None: 'solved')
    config, policy, pomdp, converged = stages.refit(
        data, point, summary, {'result': SimpleNamespace(value=None)}, default_config,
        spec.fit, None, spec.seed, 3, None)
    assert policy == 'solved' and pomdp is None and converged
    resample = stages.refit_data(data['all'], [spec.seed, 4, 3])
    assert len(resample.episodes) == len(data['all'].episodes) == 8
    assert resample.epochs != data['all'].epochs or not np.array_equal(
        resample.observation, data['all'].observation)
    want = fitting.fit(resample, default_config, spec.fit['hold'], n_init=1, seed=spec.seed,
                       tol=spec.fit['tol'], max_iter=spec.fit['max_iter'], bootstrap=0,
                       prior=True)
    assert config.data['stream'] == summary['config'].data['stream']
    np.testing.assert_allclose(config.data['observation']['prior'],
                               fitting.fitted_data(want, default_config)['observation']['prior'],
                               rtol=0, atol=1e-9)
    assert config.data['observation']['prior'] != summary['config'].data['observation']['prior']
