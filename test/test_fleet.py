"""The plant of cells (hrc-fleet, docs/FLEET.md): the plant file, the promotion rule, the
pipeline's state machine and the drift test's pieces without Ray; then `hrc-fleet run` on the
session's embedded Ray (one per test process, 2 CPUs, a small object store, no dashboard):

- a plant of four small cells (generated recordings at full model size: one whose people
  accept readily and drift closer, 4000 epochs of them (the promotion check's interval
  narrows with the epochs; people who decline most requests kept even 4000 epochs within the
  fit's error of no change); one unchanged; one whose bag is corrupt; and a cell of
  one-priority, one-duration tasks (rho = sigma = 1) whose people decline most requests and
  drift closer and which plans with the POMDP: solver both, selector pomdp, running
  the POMDP policy its `pomdp_policy` names), with `--apply` against real decision nodes
  running in the two drifted cells' namespaces: both drifted cells are detected and
  promoted, the unchanged one kept, the corrupt one reported, every output there and
  loadable, and each node reports the new policy (and the POMDP cell's node the new POMDP
  policy); the POMDP cell is small because a full-size POMDP solve takes half a minute and
  the cell solves eight (an MDP and a POMDP for the fit and for each of its three refits:
  three, not the plant's five, which were 55 of its 82 s, 2026-12-07; the drifted cell keeps
  five, with three its interval reached above zero);
- a worker SIGKILLed in the middle of a drift simulation (its pid recorded from inside the
  task): Ray retries it on another worker, the report is the one of the run without kill
  and says what Ray redid;
- the promotion check on the issue's two cases (a truly better cell promoted, a cell of the
  default world kept), and the engine's edges (a cluster that cannot be joined, Ctrl-C).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import replace
from types import SimpleNamespace
from functools import partial
from pathlib import Path

import numpy as np
import pytest
from conftest import PLANT_TIMEOUT

from hrc_ros.core.config import load_config
from hrc_ros.core.learning import fit as fitting
from hrc_ros.core.parallel import descendants
from hrc_ros.core.plant import drift
from hrc_ros.core.plant.pipeline import (FAILED, KEEP, PROMOTE, CellPipeline, Ref,
                                         run_stage)
from hrc_ros.core.plant.spec import PlantError, load_plant
from hrc_ros.core.plant.stages import CellError, check_memory
from hrc_ros.core.model import HRCModel

REPO = Path(__file__).resolve().parents[1]
DRIFTED_WORLD = {'model': {'p_accept': [0.05, 0.35, 0.7],
                           'p_delta': [[0.05, 0.65, 0.30], [0.05, 0.55, 0.40],
                                       [0.02, 0.38, 0.60]]}}
# people who accept readily and drift closer: planning with the default costs a regret of
# 3.01 +- 0.37 per episode there (1000 paired episodes against the world's own optimum, which
# refuses more requests: 0.82 against 0.47 per episode)
EAGER_CLOSE = {'model': {'p_accept': [0.7, 0.95, 0.99],
                         'p_delta': [[0.05, 0.65, 0.30], [0.05, 0.55, 0.40],
                                     [0.02, 0.38, 0.60]]}}
PLANT = """\
plant: test
defaults:
  policy: {policy}
  drift: {{window: 1000, simulations: 39}}
  fit: {{bootstrap: 20}}
  evaluate: {{episodes: 300, refits: 5}}
cells:
  - name: drifted
    namespace: /fleet_drifted
    generate: {{world: {eager_close}, episodes: 80, epochs: 50, seed: 1}}
  - name: unchanged
    namespace: /fleet_unchanged
    generate: {{world: {{}}, episodes: 20, epochs: 50, seed: 2}}
  - name: corrupt
    namespace: /fleet_corrupt
    recordings: corrupt
  - name: pomdp
    namespace: /fleet_pomdp
    base: {small_base}
    policy: {small_policy}
    pomdp_policy: {small_pomdp}
    solver: both
    selector: pomdp
    pomdp: {{episodes: 10, rounds: 0}}
    evaluate: {{refits: 3}}
    generate: {{world: {world}, episodes: 80, epochs: 50, seed: 3}}
"""


# -- the plant file ---------------------------------------------------------------------------
def write_plant(tmp_path, text: str) -> Path:
    path = tmp_path / 'plant.yaml'
    path.write_text(text)
    return path


CELL = '  - name: a\n    recordings: x.csv\n'


@pytest.mark.parametrize('text, message', [
    ('cells: []\n', 'cells must be a non-empty list'),
    ('cells:\n' + CELL + CELL, "the name 'a' is used by another cell"),
    ('cells:\n  - name: a b\n    recordings: x.csv\n', 'name must be letters'),
    ('cells:\n  - name: a\n', 'give either recordings'),
    ('cells:\n' + CELL + '    drift: {window: 5}\n', 'drift.window must be an integer in'),
    ('cells:\n' + CELL + '    drift: {windw: 500}\n', "unknown key drift.windw"),
    ('cells:\n' + CELL + '    solver: sarsop\n', 'solver must be mdp or pomdp or both'),
    ('cells:\n' + CELL + '    selector: pomdp\n', 'set solver: pomdp or both'),
    ('cells:\n' + CELL + '    pomdp_policy: p.npz\n', 'pomdp_policy is the running POMDP '
     'policy of a cell whose selector is pomdp or fib; this one runs paper'),
    ('cells:\n' + CELL + '    namespace: bad ns\n',
         "namespace 'bad ns' has the name 'bad ns', which must start with a letter"),
    ('cells:\n' + CELL + '    fit: {hold: [p_acept]}\n', "unknown parameter family 'p_acept'"),
    ('cells:\n' + CELL + '    fit: {prior: 3}\n', 'cells[0] (a): fit.prior must be true or false, '
     'got 3'),
    ('defaults:\n  fit: {stream: yes please}\ncells:\n' + CELL,
     "defaults: fit.stream must be true or false, got 'yes please'"),
    ('defaults:\n  recordings: x\ncells:\n' + CELL, 'recordings is set per cell'),
    ('cells:\n' + CELL + '  - name: b\n    namespace: /a\n    recordings: y.csv\n',
     'namespace /a is also the namespace of cell a'),
    ('cells:\n' + CELL + '    evaluate: {worlds: 10}\n',
     'evaluate.worlds: the held-out check and its bootstrap worlds are gone'),
    ('cells:\n' + CELL + '    evaluate: {refits: 1}\n', 'evaluate.refits must be an integer in'),
    ('cells:\n' + CELL + '    promote: {guards: [refused]}\n',
     'promote.guards must be a list of guards among refused_requests'),
    ('cells: [\n', 'is not valid YAML'),
    ('celss: []\n', "unknown top-level key 'celss'"),
    # a key given twice: YAML keeps the second silently (a review ran the second recordings)
    ('cells:\n' + CELL + '    recordings: y.csv\n', 'the key cells.recordings is given twice'),
    # a generated world that makes no configuration of its base: the plant file's mistake,
    # refused before any work (it failed the cell after the others had run)
    ('cells:\n  - name: g\n    generate: {world: {model: {p_accept: [0.05, 0.35, 1.7]}}}\n',
     'cells[0] (g): generate.world: model.p_accept[2] = 1.7 is not a probability'),
])
def test_a_bad_plant_file_is_refused_in_one_line(tmp_path, text, message):
    with pytest.raises(PlantError) as error:
        load_plant(write_plant(tmp_path, text))
    assert message in str(error.value) and '\n' not in str(error.value)


def test_a_plant_file_too_large_is_refused_before_it_is_parsed(tmp_path):
    path = write_plant(tmp_path, 'cells:\n' + CELL + '#' * 1_100_000 + '\n')
    with pytest.raises(PlantError, match='more than the 1,048,576 a YAML plant file may have'):
        load_plant(path)


def test_the_command_refuses_a_bad_plant_with_exit_2_before_any_work(tmp_path, capsys):
    from hrc_ros.tools.fleet import main
    path = write_plant(tmp_path, 'cells:\n' + CELL + '    run: sometimes\n')
    assert main(['run', str(path), '--out', str(tmp_path / 'out')]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith('hrc-fleet: error: ') and 'run must be on_drift or always' in err
    assert len(err.splitlines()) == 1 and not (tmp_path / 'out').exists()


def test_defaults_and_paths_resolve_against_the_plant_file(tmp_path):
    path = write_plant(tmp_path, 'defaults:\n  drift: {window: 300}\n  run: always\n'
                       'cells:\n' + CELL + '    drift: {alpha: 0.01}\n'
                       '  - name: b\n    base: paper\n    recordings: [one.csv, /abs/two]\n')
    a, b = load_plant(path).cells
    assert a.drift['window'] == 300 and a.drift['alpha'] == 0.01 and a.run == 'always'
    assert b.drift['alpha'] == 0.05 and b.namespace == '/b' and b.selector == 'paper'
    assert a.recordings == (str(tmp_path / 'x.csv'),)
    assert b.recordings == (str(tmp_path / 'one.csv'), '/abs/two')
    assert b.base.endswith('config/paper.yaml')


def test_a_pomdp_cell_runs_the_pomdp_policy_it_names_and_a_wrong_one_fails_that_cell(tmp_path):
    """`pomdp_policy`: the POMDP policy a pomdp / fib cell runs now (the shadow check's running
    side), by default the shipped one solved for its base; one solved for another
    configuration fails that cell, with the reason, and not the others."""
    import shutil
    from hrc_ros.core.paths import share_dir
    from hrc_ros.tools.fleet import prepare
    shipped = share_dir() / 'policies' / 'pomdp'
    shutil.copyfile(shipped / 'fail_safe_unaware.npz', tmp_path / 'unaware.npz')
    shutil.copyfile(shipped / 'default.npz', tmp_path / 'running.npz')
    pomdp_cell = '    solver: both\n    selector: pomdp\n'
    path = write_plant(tmp_path, 'cells:\n' + CELL + pomdp_cell
                       + '  - name: b\n    recordings: x.csv\n' + pomdp_cell
                       + '    pomdp_policy: running.npz\n'
                       + '  - name: c\n    recordings: x.csv\n' + pomdp_cell
                       + '    pomdp_policy: unaware.npz\n')
    (tmp_path / 'x.csv').write_text('')
    pipelines, objects = prepare(load_plant(path), tmp_path / 'out')
    assert objects['@running:a']['pomdp'].path == str(shipped / 'default.npz')
    assert objects['@running:b']['pomdp'].path == str(tmp_path / 'running.npz')
    a, b, c = pipelines
    assert a.error is None and b.error is None
    assert c.error.startswith('running policy: ') and 'was solved for configuration' in c.error


# -- the promotion rule -----------------------------------------------------------------------
def corrected_figure(mean, half, in_sample=None, refits=10):
    """A metric of the check as check.corrected gives it."""
    return {'mean': mean, 'low': mean - half, 'high': mean + half, 'half_width': half,
            'in_sample': mean if in_sample is None else in_sample, 'refits': refits,
            'in_sample_half_width': 0.1, 'optimism': 0.0, 'optimism_sd': 1.0,
            'new': 1.0, 'running': 1.0}


def figures(cost, collisions=(0.0, 0.1), refused=(0.0, 0.1), tasks=(0.0, 0.1)):
    return {'discounted_cost': corrected_figure(*cost),
            'collision_epochs': corrected_figure(*collisions),
            'refused_requests': corrected_figure(*refused),
            'tasks_completed': corrected_figure(*tasks)}


@pytest.mark.parametrize('shadow, guards, decision, why', [
    (figures((-2.0, 1.0)), (), PROMOTE, 'cheaper'),
    (figures((-2.0, 2.1)), (), KEEP, 'not cheaper with 95% confidence'),
    (figures((-2.0, 2.0)), (), KEEP, 'not cheaper with 95% confidence'),
    (figures((-2.0, float('nan'))), (), KEEP, 'not cheaper'),
    # the safety guard: more collision epochs with 95% confidence keeps, and says so
    (figures((-2.0, 1.0), collisions=(0.5, 0.4)), (), KEEP,
     'more collision epochs with 95% confidence, the safety guard'),
    # within noise of no change it does not block what is cheaper
    (figures((-2.0, 1.0), collisions=(0.05, 0.1)), (), PROMOTE, 'cheaper'),
    # not cheaper and more collision epochs: the keep's reason names both (the issue: a keep
    # named only the cost, not the held-out collisions)
    (figures((+1.0, 0.5), collisions=(5.34, 0.4)), (), KEEP,
     'collision epochs new - running +5.340 [+4.940, +5.740] per episode (95%), more with 95% '
     'confidence'),
    # refused requests are priced by the cost: no guard on them unless the plant sets one
    (figures((-3.0, 0.5), refused=(1.04, 0.3)), (), PROMOTE, 'cheaper'),
    (figures((-3.0, 0.5), refused=(1.04, 0.3)), ('refused_requests',), KEEP,
     "kept by the plant's guard (refused_requests)"),
    (figures((-3.0, 0.5), tasks=(-1.0, 0.3)), ('tasks_completed',), KEEP, 'cost given up'),
    (figures((-3.0, 0.5), tasks=(+1.0, 0.3)), ('tasks_completed',), PROMOTE, 'cheaper'),
])
def test_the_promotion_rule(shadow, guards, decision, why):
    from hrc_ros.core.plant.check import decide
    got, reason, blocked = decide(shadow, guards)
    assert got == decision and why in reason, reason
    assert bool(blocked) == (decision == KEEP and bool(guards))


def test_without_refits_nothing_is_promoted_and_the_collisions_are_named():
    """The case study's bag (one episode): no refits, so no interval that carries the fitting
    error; in-sample cheaper with 95% confidence over the episodes is not enough, and the
    in-sample collision epochs, higher, are named."""
    from hrc_ros.core.plant.check import decide
    unchecked = {'discounted_cost': corrected_figure(-2.86, 0.98, refits=0),
                 'collision_epochs': corrected_figure(0.32, 0.12, refits=0)}
    decision, reason, _ = decide(unchecked, unchecked='the recordings hold 1 episode')
    assert decision == KEEP and 'could not be bounded (the recordings hold 1 episode)' in reason
    assert 'more collision epochs: +0.320 [+0.200, +0.440]' in reason


def test_a_guard_that_keeps_a_cell_reports_the_cost_it_gave_up():
    from hrc_ros.core.plant.check import decide
    _, reason, (blocked,) = decide(figures((-3.01, 0.47), refused=(1.04, 0.3)),
                                   ('refused_requests',))
    assert blocked['cost_given_up']['mean'] == -3.01
    assert 'cost given up: cost new - running -3.010 [-3.480, -2.540]' in reason


def test_the_estimate_subtracts_the_refits_mean_error_and_its_interval_predicts_one_more():
    """check.corrected: in-sample minus the refits' mean error; half-width t(0.975, R - 1)
    sqrt(s_f^2 (1 + 1/R) + v_in + mean(v_b) / R), the fitting error's variance s_f^2 being the
    errors' variance less their episodes' noise; with no spread among the refits, still the
    in-sample episodes' noise (at t's width); with fewer than two refits the in-sample figures
    as they are."""
    from scipy.stats import t as student
    from hrc_ros.core.plant.check import Z95, combine, corrected
    inside = {'mean': -4.0, 'half_width': 0.3, 'new': 10.0, 'running': 14.0}
    errors = [-1.0, -3.0, -2.0, -0.5, -3.5]
    noise = [0.2, 0.1, 0.3, 0.2, 0.2]
    c = corrected(inside, errors, noise)
    fitting = np.var(errors, ddof=1) - 0.2
    expected = student.ppf(0.975, 4) * np.sqrt(fitting * 1.2 + (0.3 / Z95) ** 2 + 0.2 / 5)
    assert c['mean'] == pytest.approx(-4.0 + 2.0) and c['optimism'] == pytest.approx(-2.0)
    assert c['half_width'] == pytest.approx(expected)
    assert c['fitting_sd'] == pytest.approx(np.sqrt(fitting))
    # counting the refits' episodes' noise as fitting error would widen it
    assert corrected(inside, errors)['half_width'] > c['half_width']
    assert c['low'] < -2.0 < c['high'] and c['refits'] == 5
    flat = corrected({**inside, 'half_width': 9.0}, [-2.0, -2.0, -2.0])   # no spread at all
    assert flat['half_width'] == pytest.approx(student.ppf(0.975, 2) * 9.0 / Z95)
    assert flat['mean'] == pytest.approx(-2.0)
    alone = corrected(inside, [-2.0])
    assert (alone['mean'], alone['half_width'], alone['optimism']) == (-4.0, 0.3, None)
    rows = [{'discounted_cost': [e - 1.0, -1.0, v], 'collision_epochs': [0.0, 0.0, 0.0]}
            for e, v in zip(errors, noise)]
    both = combine({'discounted_cost': inside, 'collision_epochs': {**inside, 'mean': 0.0}},
                   rows)
    assert both['discounted_cost']['half_width'] == pytest.approx(c['half_width'])
    assert set(both) == {'discounted_cost', 'collision_epochs'}


# -- the pipeline as a state machine ----------------------------------------------------------
def pipeline_of(tmp_path, run='on_drift', bootstrap=25, simulations=39, extra=''):
    path = write_plant(tmp_path, f'cells:\n{CELL}    run: {run}\n    fit: {{bootstrap: '
                       f'{bootstrap}}}\n    drift: {{simulations: {simulations}}}\n{extra}')
    spec = load_plant(path).cells[0]
    return CellPipeline(spec, str(tmp_path / 'cells' / 'a'), rho=3, sigma=3)


READ = {'epochs': 1000, 'episodes': 20, 'window_epochs': 1000, 'issues': 0,
        'first_issues': [], 'files': ['x.csv']}
DRIFT = {'statistic': 50.0, 'loglik_running': -10.0, 'loglik_refit': 15.0, 'impossible': ''}


def keys(jobs):
    return [j.key for j in jobs]


def test_no_drift_keeps_the_cell_without_fitting(tmp_path):
    p = pipeline_of(tmp_path)
    assert keys(p.start()) == ['read'] and p.start()[0].where == 'driver_node'
    assert keys(p.done('read', READ)) == ['drift']
    nulls = p.done('drift', DRIFT)
    assert keys(nulls) == ['null.0', 'null.1', 'null.2', 'null.3']     # 39 in chunks of 10
    assert sum(len(j.args[-1]) for j in nulls) == 39
    assert p.done('null.0', {'statistics': [60.0] * 10}) == []
    p.done('null.1', {'statistics': [40.0] * 10})
    p.done('null.2', {'statistics': [40.0] * 10})
    out = p.done('null.3', {'statistics': [40.0] * 9})
    assert keys(out) == ['outputs'] and out[0].args[1:] == (None,) * 4
    assert p.entry['decision'] == KEEP and p.entry['drift_p'] == pytest.approx(11 / 40)
    assert 'no drift' in p.entry['reason'] and 'the last 1000 epochs' in p.entry['reason']
    write = p.done('outputs', {'files': ['cell_report.json']})
    assert keys(write) == ['write'] and write[0].where == 'driver'
    assert p.done('write', {'files': ['cell_report.json']}) == [] and p.finished


def test_drift_starts_the_fit_and_a_failure_fails_only_that_cell(tmp_path):
    p = pipeline_of(tmp_path)
    p.start()
    p.done('read', READ)
    p.done('drift', DRIFT)
    for i in range(3):
        p.done(f'null.{i}', {'statistics': [10.0] * 10})
    fit = p.done('null.3', {'statistics': [10.0] * 9})
    assert keys(fit) == ['fit'] and p.entry['drift_p'] == 0.025
    boots = p.done('fit', {'iterations': 12, 'loglik': -5.0})
    assert keys(boots) == ['boot.0', 'boot.1', 'boot.2']
    assert [len(j.args[-1]) for j in boots] == [10, 10, 5]
    assert p.done('boot.1', {'resamples': 10}) == []
    failed = p.done('boot.0', {'error': 'bootstrap: out of memory'})
    assert keys(failed) == ['write'] and p.entry['decision'] == FAILED
    assert p.entry['reason'] == 'bootstrap: out of memory'
    report = json.loads(failed[0].args[1]['cell_report.json'])
    assert report['decision'] == FAILED and report['drift_p'] == 0.025
    assert p.done('boot.2', {'resamples': 5}) == []        # late results change nothing
    p.done('write', {'files': ['cell_report.json']})
    assert p.finished


def paired_figures(cost, collisions=0.0, refused=0.0):
    """The shadow stage's in-sample facts: each metric's paired mean and its episodes'
    half-width."""
    def m(mean, half=0.2):
        return {'mean': mean, 'half_width': half, 'low': mean - half, 'high': mean + half,
                'new': 1.0, 'running': 1.0}
    return {'discounted_cost': m(cost), 'collision_epochs': m(collisions),
            'refused_requests': m(refused), 'tasks_completed': m(0.0),
            'collision_stuck': m(0.0), 'world': 'in-sample', 'episodes': 300, 'epochs': 50,
            'seed': 0, 'selector': 'paper'}


def refit_rows(draws, cost_errors, collision_errors=None):
    """The refits stage's rows: per metric [in the refit's world, in the fitted world]."""
    collision_errors = collision_errors or [0.0] * len(draws)
    return {'rows': [{'draw': b, 'converged': True, 'discounted_cost': [e - 1.0, -1.0, 0.01],
                      'collision_epochs': [c, 0.0, 0.0], 'refused_requests': [0.0, 0.0, 0.0],
                      'tasks_completed': [0.0, 0.0, 0.0], 'collision_stuck': [0.0, 0.0, 0.0]}
                     for b, e, c in zip(draws, cost_errors, collision_errors)]}


def test_run_always_fits_beside_the_drift_test_and_waits_for_it(tmp_path):
    """The fit starts beside the drift test; the shadow check (in-sample figures and the
    refits, side by side) waits for the p-value and the solve; the decision waits for every
    refit and rests on the corrected figures: in-sample cheaper by 1.0, the refits' errors
    -2 +- 1, so the estimate +1.0 [...] keeps it."""
    p = pipeline_of(tmp_path, run='always', bootstrap=0, simulations=9)
    p.start()
    first = p.done('read', READ)
    assert keys(first) == ['drift', 'fit']
    summary = p.done('fit', {'iterations': 3, 'loglik': -1.0})
    assert keys(summary) == ['summary'] and summary[0].args[:2] == (Ref('fit'),
                                                                    Ref('@base:a'))
    solve = p.done('summary', {'moved': [], 'warnings': [], 'bootstrap': 0,
                               'config_sha256': 'abc'})
    assert keys(solve) == ['mdp']
    assert keys(p.done('drift', DRIFT)) == ['null.0']
    assert p.done('mdp', {'iterations': 1, 'converged': True, 'residual': 0.0}) == []
    check = p.done('null.0', {'statistics': [100.0] * 9})     # no drift, but run: always
    assert p.entry['drift_p'] == 1.0
    assert keys(check) == ['shadow'] + [f'refit.{i}' for i in range(10)]
    assert [j.args[-1] for j in check[1:]] == [[i] for i in range(10)]   # each refit's draw
    assert p.done('shadow', paired_figures(-1.0)) == []       # waits for the refits
    errors = [-2.0, -1.0, -3.0, -2.0, -1.0, -3.0, -2.0, -2.5, -1.5, -2.0]
    for i in range(9):
        assert p.done(f'refit.{i}', refit_rows([i], errors[i:i + 1])) == []
    outputs = p.done('refit.9', refit_rows([9], errors[9:]))
    assert keys(outputs) == ['outputs'] and p.entry['decision'] == KEEP
    cost = p.entry['cost_difference']
    assert cost['in_sample'] == -1.0 and cost['mean'] == pytest.approx(1.0)
    assert cost['low'] < 1.0 < cost['high'] and cost['refits'] == 10
    assert 'not cheaper with 95% confidence' in p.entry['reason']
    assert p.entry['shadow']['errors']['discounted_cost'] == pytest.approx(errors)
    # the report says how the refits were made: resampled episodes (recordings simulated
    # from the fit were tried and dropped; the report said so until 2026-12-06)
    world = p.entry['shadow']['world']
    assert 'refits of resampled episodes' in world and 'simulated' not in world
    assert outputs[0].args[-1] == Ref('shadow')


def through_the_check(p, shadow, errors=(), collision_errors=None, read=READ):
    """A `run: always` pipeline driven through read, fit, the drift test (no drift), the solve
    and the shadow check with these in-sample figures and refits' cost (and collision)
    errors: (the jobs after the drift test, the jobs after the last result)."""
    p.start()
    p.done('read', read)
    p.done('fit', {'iterations': 3, 'loglik': -1.0})
    p.done('summary', {'moved': [], 'warnings': [], 'bootstrap': 0, 'config_sha256': 'abc'})
    p.done('drift', DRIFT)
    p.done('mdp', {'iterations': 1, 'converged': True, 'residual': 0.0})
    checks = p.done('null.0', {'statistics': [100.0] * 9})
    last = p.done('shadow', shadow)
    collisions = collision_errors or [0.0] * len(errors)
    for i, (error, collision) in enumerate(zip(errors, collisions)):
        last = p.done(f'refit.{i}', refit_rows([i], [error], [collision]))
    return checks, last


def test_a_cell_of_too_few_episodes_is_checked_without_refits_and_its_report_says_so(tmp_path):
    """Fewer than stages.MIN_EPISODES episodes: the shadow check runs alone, the cell is kept,
    and the entry's shadow world says that nothing corrected the interval (it said, as for a
    refitted cell, that the interval carries the fitting error)."""
    from hrc_ros.core.plant import check
    from hrc_ros.core.plant.stages import MIN_EPISODES
    p = pipeline_of(tmp_path, run='always', bootstrap=0, simulations=9)
    checks, outputs = through_the_check(p, paired_figures(-3.0),
                                        read={**READ, 'episodes': MIN_EPISODES - 1})
    assert keys(checks) == ['shadow']                           # no refits
    assert keys(outputs) == ['outputs'] and p.entry['decision'] == KEEP
    assert p.entry['shadow']['world'] == check.WORLD_UNCORRECTED
    assert 'leaves the fitting error out' in p.entry['shadow']['world']
    assert p.entry['cost_difference']['optimism'] is None


def test_a_guard_the_plant_file_sets_keeps_a_cheaper_cell_and_its_entry_has_the_cost_given_up(
        tmp_path):
    """`promote: {guards: [refused_requests]}` in the plant file, through the cell's pipeline:
    in-sample -3 cheaper with refits' errors about -0.5 (promote on the cost alone), but 1.0
    more refused requests per episode: kept, and the entry names the guard and the cost."""
    p = pipeline_of(tmp_path, run='always', bootstrap=0, simulations=9,
                    extra='    promote: {guards: [refused_requests]}\n')
    through_the_check(p, paired_figures(-3.0, refused=1.0),
                      [-0.5, -0.4, -0.6, -0.5, -0.45, -0.55, -0.5, -0.5, -0.4, -0.6])
    assert p.entry['decision'] == KEEP
    assert "kept by the plant's guard (refused_requests)" in p.entry['reason']
    (kept,) = p.entry['guards']['kept_by']
    assert kept['guard'] == 'refused_requests' and kept['cost_given_up']['high'] < 0
    assert p.entry['guards']['plant'] == ['refused_requests']


def test_a_cheaper_policy_with_more_collision_epochs_is_kept_by_the_safety_guard(tmp_path):
    """In-sample -3, refits' errors -0.5 +- 0.3: the estimate -2.5 with an interval below
    zero, and the collision epochs higher with 95% confidence keep it, named in the reason."""
    p = pipeline_of(tmp_path, run='always', bootstrap=0, simulations=9)
    through_the_check(p, paired_figures(-3.0, collisions=0.8),
                      [-0.5, -0.2, -0.8, -0.5, -0.4, -0.6, -0.5, -0.3, -0.7, -0.5], [0.1] * 10)
    assert p.entry['cost_difference']['high'] < 0
    assert p.entry['decision'] == KEEP
    assert p.entry['reason'].startswith('more collision epochs with 95% confidence')
    assert p.entry['collision_epochs']['mean'] == pytest.approx(0.7)


def test_a_stage_error_or_bug_becomes_the_cells_reason():
    facts, payload = run_stage('drift_null', None, None, None, None, [])
    assert payload is None and facts['error'].startswith('drift_null: TypeError')
    facts, _ = run_stage('read', ['/nonexistent/recordings.csv'], 3, 3, '/a', 100)
    assert facts['error'].startswith('recordings: /nonexistent/recordings.csv')


# -- the stages' refusals ---------------------------------------------------------------------
def recorded(config, episodes=10, epochs=50, seed=0):
    from hrc_ros.core.mdp.policy import default_policy_path, load_policy
    from hrc_ros.core.study.evaluation import BatchSimulator, episodes_of
    model = HRCModel(config)
    policy = load_policy(default_policy_path(config), config)
    scenarios, seeds = episodes_of(model, 'random', episodes, epochs, seed)
    result = BatchSimulator(model, policy).run(scenarios, seeds, 'paper', explore=0.2,
                                               record=True)
    return fitting.prepare(result.recordings(model))


def test_a_solve_over_its_memory_limit_and_a_fit_that_does_not_converge_fail_the_cell(
        default_config, model):
    with pytest.raises(CellError, match='more than the cell.s max_memory_mb'):
        check_memory(model, 1, 'the MDP solve')
    data = recorded(default_config, episodes=4)
    with pytest.raises(CellError, match='EM did not converge in 1 iterations'):
        from hrc_ros.core.plant.stages import fit_point
        fit_point({'all': data}, default_config, {'hold': (), 'starts': 1, 'tol': 1e-12,
                                                  'max_iter': 1}, 0)


def test_bootstrap_summary_applies_fits_rules_to_resamples_made_elsewhere(default_config):
    data = recorded(default_config, episodes=12)
    whole = fitting.fit(data, default_config, n_init=1, bootstrap=6, max_iter=200)
    point = replace(whole, interval=None, samples=None, effective=None,
                    warnings=fitting.fit(data, default_config, n_init=1, bootstrap=0,
                                         max_iter=200).warnings)
    again = fitting.with_bootstrap(point, whole.samples)
    np.testing.assert_array_equal(again.interval, whole.interval)
    np.testing.assert_array_equal(again.effective, whole.effective)
    assert again.warnings == whole.warnings


# -- the report's pieces ----------------------------------------------------------------------
def test_a_moved_parameters_interval_holds_its_value_and_is_never_narrower_than_its_support():
    """One episode (the case study's bag): every resample is that episode, the bootstrap's
    intervals have no width, and 57 parameters 'moved'; refitted from the estimate, one
    stopped a rounding step beside it: fitted 0.0819, interval [0.0820, 0.0820]."""
    from hrc_ros.core.plant.stages import moved_parameters, own_interval, parameter_interval
    names = list(fitting.PARAMETER_NAMES)
    i = names.index('p_delta[ea=0][Delta=+1]')
    params = fitting.Params.from_config(load_config(REPO / 'config' / 'default.yaml'))
    fitted = params.copy()
    fitted.p_delta = np.array([[0.918, 0.0001, 0.0819], [0.1, 0.7, 0.2], [0.05, 0.55, 0.4]])
    vector = fitted.vector()
    interval = np.stack([vector, vector])
    interval[:, i] = 0.0820
    support = np.full(len(names), 12.0)
    result = SimpleNamespace(params=fitted, base=params, hold=(), interval=interval,
                             support=support)
    low, high = parameter_interval(result, i)
    assert low <= 0.0819 <= high
    own = own_interval(0.0819, 12.0)
    assert (low, high) == pytest.approx(own) and high - low > 0.2
    moved = {m['name']: m for m in moved_parameters(result)}
    assert 'p_delta[ea=0][Delta=+1]' not in moved          # 0.10 is inside [0.014, 0.35]
    assert moved['p_delta[ea=0][Delta=-1]']['ci95'][0] > 0.15   # 0.918 of 12: it did move
    for m in moved.values():
        assert m['ci95'][0] <= m['fitted'] <= m['ci95'][1]
        assert m['ci95'][1] - m['ci95'][0] >= np.subtract(*own_interval(m['fitted'], 12)[::-1])


def test_the_drift_line_names_the_epochs_tested_and_a_p_value_at_alpha():
    d = {'simulations': 99, 'p': 0.05, 'alpha': 0.05, 'statistic': 30.11, 'window_epochs': 20,
         'window': 2000, 'null_median': 18.2, 'impossible': ''}
    words = drift.describe(d)
    assert 'all 20 recorded epochs (fewer than the window of 2000)' in words
    assert 'p = 0.050 (= 5/100' in words and 'exactly alpha 0.05, not below it: no drift' in words
    words = drift.describe({**d, 'p': 0.01, 'window_epochs': 2000})
    assert 'the last 2000 epochs' in words and 'below alpha 0.05: drift' in words


def test_the_markdown_says_the_run_mode_warnings_guards_and_retries_and_the_plot_has_a_legend(
        tmp_path):
    from hrc_ros.core.plant import report as reporting
    cost = corrected_figure(-3.01, 0.47, in_sample=-3.5)
    entry = {'cell': 'a', 'namespace': '/a', 'decision': KEEP, 'reason': 'kept', 'run': 'always',
             'drift_p': 0.5, 'drift': None, 'cost_difference': cost,
             'collision_epochs': corrected_figure(0.0, 0.1),
             'refused_requests': corrected_figure(1.04, 0.3), 'moved': [],
             'read': {'epochs': 20, 'episodes': 1, 'issues': 1,
                      'first_issues': ['x.csv:7: the episode is cut there']},
             'fit': {'warnings': ['only 1 episode: bootstrap intervals over episodes need more '
                                  'to mean much']},
             'guards': {'safety': 'collision_epochs', 'plant': ['refused_requests'],
                        'kept_by': [{'guard': 'refused_requests',
                                     'figure': corrected_figure(1.04, 0.3),
                                     'cost_given_up': cost}]},
             'retries': [{'stage': 'null.2', 'attempts': 2,
                          'workers': [{'pid': 11, 'node': 'n1'}, {'pid': 12, 'node': 'n2'}]}]}
    plant = {'plant': 'p', 'started': 'now', 'seconds': 1.0, 'engine': 'Ray (x, 2 CPUs)',
             'decisions': {'promote': 0, 'keep': 1, 'failed': 0}, 'cells': [entry],
             'lost_nodes': [{'node': 'n2' * 10, 'address': '10.0.0.2', 'after_seconds': 31.0,
                             'reason': 'raylet died'}], 'retried_tasks': 1}
    text = reporting.markdown(plant)
    assert 'run: always (fitted and checked whatever the drift test says)' in text
    assert '- only 1 episode: bootstrap intervals' in text and 'x.csv:7: the episode' in text
    # a keep on few episodes says so (the check's power by recording size, docs/FLEET.md)
    assert '- kept on 1 recorded episode: the fitting error of so few' in text
    many = {**entry, 'read': {**entry['read'], 'episodes': 200}}
    promoted = {**entry, 'decision': PROMOTE}
    unchecked = {k: v for k, v in entry.items() if k != 'cost_difference'}   # no drift: no fit
    for other in (many, promoted, unchecked):
        assert 'recorded episode' not in reporting.markdown({**plant, 'cells': [other]})
    assert 'the cost it gave up: -3.010 [-3.480, -2.540] per episode' in text
    assert 'Ray ran null.2 2 times (workers pid 11 on n1, pid 12 on n2)' in text
    assert 'nodes lost: n2n2n2n2n2n2 (10.0.0.2) after 31 s: raylet died' in text
    assert '[ray.log](ray.log)' in text
    serial = reporting.markdown({**plant, 'engine': reporting.SERIAL_ENGINE})
    assert 'ray.log' not in serial and 'without Ray' in serial      # --serial writes none
    figure = reporting.plant_figure([entry, {**entry, 'cell': 'b', 'decision': PROMOTE}])
    legend = [t.get_text() for t in figure.axes[0].get_legend().get_texts()]
    assert any(t.startswith('promote') for t in legend) and any(t.startswith('keep')
                                                                for t in legend)
    assert any('in-sample' in t for t in legend)


def test_a_cell_without_refits_shows_its_interval_as_the_episodes_alone_everywhere():
    """A cell of too few episodes for refits is kept on an interval over the episodes alone
    (check.corrected): the table, the check's section and the plot say so, not that the
    interval carries the fitting error; the table counts every warning its section lists."""
    from hrc_ros.core.plant import check
    from hrc_ros.core.plant import report as reporting
    in_sample = {'mean': -2.86, 'half_width': 0.98, 'new': 10.0, 'running': 12.86}
    cost = check.corrected(in_sample, [], [])
    assert cost['optimism'] is None and cost['half_width'] == 0.98
    entry = {'cell': 'case_study', 'namespace': '/', 'decision': KEEP, 'reason': 'kept',
             'run': 'always', 'drift_p': 0.5, 'cost_difference': cost, 'moved': [],
             'read': {'epochs': 20, 'episodes': 1, 'issues': 1,
                      'first_issues': ['x.csv:7: the episode is cut there']},
             'fit': {'warnings': ['only 1 episode']},
             'shadow': {'world': check.WORLD_UNCORRECTED, 'refits': 0, 'episodes': 1000,
                        'epochs': 50, 'seed': 0, 'selector': 'paper'}}
    plant = {'plant': 'p', 'started': 'now', 'seconds': 1.0, 'engine': 'serial',
             'decisions': {'promote': 0, 'keep': 1, 'failed': 0}, 'cells': [entry],
             'lost_nodes': [], 'retried_tasks': 0}
    text = reporting.markdown(plant)
    marked = '-2.860 [-3.840, -1.880] (episodes only: no refits, fitting error not bounded)'
    row = next(line for line in text.splitlines() if line.startswith('| case_study |'))
    assert marked in row
    assert row.split(' | ')[-2] == '3'         # the fit's, the keep on 1 episode, the read's
    assert text.count('\n- ') >= 3
    assert marked in text.split('## case_study')[1]          # the check's section too
    assert 'leaves the fitting error out' in text
    assert 'refits of recordings simulated' not in text      # the method that was dropped
    legend = [t.get_text() for t in reporting.plant_figure([entry]).axes[0]
              .get_legend().get_texts()]
    assert any('no refits, fitting error not bounded' in t for t in legend)
    refitted = {**entry, 'cost_difference': corrected_figure(-2.86, 1.5)}
    assert '(episodes only' not in reporting.markdown({**plant, 'cells': [refitted]})


def episode(name: str, epochs: int, first: int = 1):
    from hrc_ros.core.learning.recordings import Recording
    k = np.arange(first, first + epochs)
    return Recording('x.csv', name, k, np.zeros((epochs, 8), dtype=int), k % 4, k % 3,
                     k % 5, np.full(epochs, -1), k + 1)


# -- the drift test's pieces ------------------------------------------------------------------
def test_simulated_recordings_keep_the_design_and_draw_moves_the_model_allows(default_config):
    data = recorded(default_config, episodes=10)
    params = fitting.Params.from_config(default_config)
    simulated = drift.simulate(data, params, np.full(9, 1 / 9), np.random.default_rng(3))
    assert np.array_equal(simulated.observation < 3, data.observation < 3)
    assert np.array_equal(simulated.answer > 0, data.answer > 0)
    moves = simulated.move[data.has_move].astype(bool)
    unique = data.unique_delta[data.has_move]
    # each row is one class of the split the recorded (d, action) makes of the three Deltas
    for row, u in zip(moves, unique):
        assert (row.sum() == 1 and u[row].all()) or np.array_equal(row, ~u)
    assert not np.array_equal(simulated.observation, data.observation)
    fitting.e_step(params, simulated)        # possible under the model it was drawn from


def test_recordings_impossible_under_the_running_model_have_p_zero(default_config):
    data = recorded(default_config, episodes=4)
    never_refuses = default_config.with_overrides({'model': {'p_accept': [1.0, 1.0, 1.0]}})
    refused = np.flatnonzero(data.answer == drift.REFUSED)
    assert refused.size
    s = drift.statistic(data, never_refuses)
    assert s.lr == np.inf and 'impossible' in s.impossible
    assert drift.p_value(s.lr, [1.0, 2.0]) == 0.0
    assert drift.p_value(3.0, [1.0, 2.0, 3.0, 4.0]) == pytest.approx(3 / 5)


# -- hrc-fleet run on Ray ---------------------------------------------------------------------
@pytest.fixture(scope='module')
def ray_session():
    """The embedded Ray of this test process (only this module uses Ray): 2 CPUs, a 150 MB
    object store, no dashboard; shut down as soon as this module's tests here are done, and
    none of its processes left behind. On xdist (conftest.py) the tests of --apply run in a
    graph unit and the engine's others in this file's own unit, each worker on a Ray of its
    own."""
    ray = pytest.importorskip('ray')
    # Ray's workers run at nice 15 by default: on a loaded machine (CI beside nothing, a
    # developer's beside other work) they would wait for everyone else; here they compete
    # as the suite's other processes do
    os.environ.setdefault('RAY_worker_niceness', '0')
    before = descendants(os.getpid())
    from hrc_ros.tools.fleet import start_ray
    assert start_ray(None, num_cpus=2, object_store_mb=150) == (True, False)
    started = descendants(os.getpid()) - before
    try:
        yield ray
    finally:
        ray.shutdown()
        deadline = time.monotonic() + 20.0
        while time.monotonic() < deadline and any(Path(f'/proc/{p}').exists() for p in started):
            time.sleep(0.1)
        left = [p for p in started if Path(f'/proc/{p}').exists()
                and (Path(f'/proc/{p}') / 'stat').read_text().split()[2] != 'Z']
        assert not left, f'Ray processes left after shutdown: {left}'


SMALL = {'model': {'rho': 1, 'sigma': 1}}


@pytest.fixture(scope='module')
def small_cell(tmp_path_factory, default_config):
    """The POMDP cell's running files: a configuration of one-priority, one-duration tasks,
    its MDP policy and its POMDP policy (solved here: no shipped one is solved for it)."""
    import yaml
    from hrc_ros.core.mdp.policy import save_policy
    from hrc_ros.core.mdp.solver import solve
    from hrc_ros.core.pomdp.policy import save_pomdp_policy
    from hrc_ros.core.pomdp.solver import solve_pomdp
    folder = tmp_path_factory.mktemp('small_cell')
    base = folder / 'small.yaml'
    base.write_text(yaml.safe_dump(default_config.with_overrides(SMALL).data))
    config = load_config(base)
    model = HRCModel(config)
    policy = save_policy(folder / 'small.npz', solve(model), config)
    pomdp = save_pomdp_policy(folder / 'small_pomdp.npz',
                              solve_pomdp(model, episodes=30, rounds=0), config)
    return {'base': str(base), 'policy': str(policy), 'pomdp': str(pomdp)}


@pytest.fixture(scope='module')
def plant_dir(tmp_path_factory, policy_path, small_cell):
    folder = tmp_path_factory.mktemp('plant')
    (folder / 'corrupt').mkdir()
    shipped = (REPO / 'bags' / 'case_study' / 'case_study_0.mcap').read_bytes()
    (folder / 'corrupt' / 'shift1.mcap').write_bytes(shipped[:len(shipped) // 2])
    (folder / 'plant.yaml').write_text(PLANT.format(
        policy=policy_path, world=json.dumps(DRIFTED_WORLD), small_base=small_cell['base'],
        eager_close=json.dumps(EAGER_CLOSE),
        small_policy=small_cell['policy'], small_pomdp=small_cell['pomdp']))
    return folder


DECISION_PARAMS = """\
/fleet_drifted/decision:
  ros__parameters:
    policy: '{policy}'
    selector: paper
    epoch_period: 0.5
    stale_timeout: 1.0
/fleet_pomdp/decision:
  ros__parameters:
    config: '{small_base}'
    policy: '{small_policy}'
    pomdp_policy: '{small_pomdp}'
    selector: pomdp
    epoch_period: 0.5
    stale_timeout: 1.0
"""


# s: the plant run of plant_run (about 40 s alone, up to 180 s beside the suite's other
# worker in a quiet CI run; at load 8, ci_bench --busy 6, it was killed at the 360 s this
# was, 2026-12-07: every process there gets about a fifth of a core); its test's timeout,
# conftest.PLANT_TIMEOUT, leaves room for small_cell's solves and the nodes before it
FLEET_TIMEOUT = 600


@pytest.fixture(scope='module')
def plant_run(ray_session, plant_dir, policy_path, small_cell, ros_domain_id):
    """`hrc-fleet run plant.yaml --apply` with a decision node running in the drifted cell's
    namespace; then a listener of our own waits for that node to report the new policy.
    hrc-fleet runs as a process of its own, a driver of the session's Ray (its GCS address):
    a native crash in a driver (Ray's core worker, rclpy) fails this fixture with the output,
    where in this process it took the test worker down (CI at load 10, 2026-12-06)."""
    from test_suite_multiprocess import Listener
    from hrc_ros.ros import conversions as conv
    from hrc_ros.ros.processes import NodeProcesses
    params = plant_dir / 'decision.yaml'
    params.write_text(DECISION_PARAMS.format(policy=policy_path, small_base=small_cell['base'],
                                             small_policy=small_cell['policy'],
                                             small_pomdp=small_cell['pomdp']))
    (plant_dir / 'logs').mkdir()
    suite = NodeProcesses(plant_dir / 'logs', [params])
    for namespace in ('/fleet_drifted', '/fleet_pomdp'):
        suite.start('decision_node', remappings=[('__ns', namespace)],
                    name=f'decision{namespace.replace("/", "_")}')
    out = plant_dir / 'out'
    try:
        fleet = fleet_process([str(plant_dir / 'plant.yaml'), '--out', str(out), '--apply',
                               '--apply-timeout', '30', '-q', '--address',
                               ray_session.get_runtime_context().gcs_address])
        try:     # below the test's timeout (conftest.PLANT_TIMEOUT), which would end the worker
            stdout, stderr = fleet.communicate(timeout=FLEET_TIMEOUT)
        except subprocess.TimeoutExpired:
            os.killpg(fleet.pid, signal.SIGKILL)
            stdout, stderr = fleet.communicate()
        finally:
            if fleet.poll() is None:
                os.killpg(fleet.pid, signal.SIGKILL)
                fleet.wait()
        code = fleet.returncode
        if code not in (0, 1):
            ray_log = out / 'ray.log'
            pytest.fail(f'hrc-fleet exited {code} (-9: killed after {FLEET_TIMEOUT} s):\n'
                        f'{stdout[-3000:]}\n{stderr[-5000:]}\n'
                        + (ray_log.read_text()[-3000:] if ray_log.exists() else ''))
        # the files set are copies named by their content (fleet_apply.live_copy), one set
        # per cell here: the test checks they are the cell's files
        lives = {cell: sorted((out / 'cells' / cell / 'live').iterdir())
                 for cell in ('drifted', 'pomdp')}
        files = {cell: {name: str(lives[cell][-1] / f'{name}.npz')
                        for name in ('policy', 'pomdp')} for cell in ('drifted', 'pomdp')}
        listener = Listener()
        seen: dict = {'drifted': [], 'pomdp': []}

        def reported():
            return (any(v.get('policy_file') == files['drifted']['policy']
                        for v in seen['drifted'])
                    and any(v.get('policy_file') == files['pomdp']['policy']
                            and v.get('pomdp_policy_file') == files['pomdp']['pomdp']
                            for v in seen['pomdp']))

        def on_diagnostics(msg):
            for status in msg.status:
                for cell in seen:
                    if status.name == f'fleet_{cell}/decision: decision':
                        seen[cell].append(conv.diagnostic_values(status))
        from diagnostic_msgs.msg import DiagnosticArray
        from hrc_ros.ros import qos
        listener.node.create_subscription(DiagnosticArray, '/diagnostics', on_diagnostics,
                                          qos.RELIABLE)
        listener.spin_until(lambda: reported() or suite.dead(), 15.0)
        listener.close()
        alive = not suite.dead()
    finally:
        suite.stop(10.0)
    report = json.loads((out / 'plant_report.json').read_text())
    return {'code': code, 'out': out, 'report': report, 'seen': seen, 'files': files,
            'lives': lives, 'stdout': stdout,
            'new_policy': files['drifted']['policy'], 'alive': alive, 'logs': suite.logs(),
            'pomdp_log': suite.log('decision_fleet_pomdp', 10 ** 6)}


def entry_of(report, cell):
    return next(e for e in report['cells'] if e['cell'] == cell)


def test_the_plant_promotes_the_drifted_cell_keeps_the_unchanged_and_reports_the_corrupt(
        plant_run):
    report, out = plant_run['report'], plant_run['out']
    assert plant_run['code'] == 1                    # a cell failed: the exit status says so
    assert [e['cell'] for e in report['cells']] == ['drifted', 'unchanged', 'corrupt', 'pomdp']
    assert report['decisions'] == {'promote': 2, 'keep': 1, 'failed': 1}
    # stdout is the decisions and where the report went, nothing of Ray's (its output of the
    # whole run, the stages' workers included, goes to OUT/ray.log)
    lines = plant_run['stdout'].splitlines()
    assert [line.split(':', 2)[:2] for line in lines[:-1]] == [
        [e['cell'], f' {e["decision"]}'] for e in report['cells']]
    assert lines[-1].startswith(f'wrote {out / "plant_report.md"}')
    assert (out / 'ray.log').is_file()
    for e in report['cells']:
        assert {'cell', 'decision', 'reason', 'drift_p', 'cost_difference'} <= set(e)

    drifted = entry_of(report, 'drifted')
    assert drifted['decision'] == PROMOTE and drifted['drift']['drifted']
    assert drifted['drift_p'] == pytest.approx(1 / 40)       # above every simulation
    cost = drifted['cost_difference']
    assert cost['high'] < 0 and cost['low'] <= cost['mean'] <= cost['high']
    assert cost['refits'] == 5 and len(drifted['shadow']['errors']['discounted_cost']) == 5
    assert cost['mean'] == pytest.approx(cost['in_sample'] - cost['optimism'])
    from hrc_ros.core.plant.check import decide
    assert decide({m: drifted[m] for m in ('collision_epochs', 'refused_requests')}
                  | {'discounted_cost': cost})[0] == PROMOTE
    moved = {m['name']: m for m in drifted['moved']}
    name = 'p_delta[ea=0][Delta=+1]'            # the world's 0.30 against the base's 0.10
    low, high = moved[name]['ci95']
    assert low > 0.1 and low <= moved[name]['fitted'] <= high

    unchanged = entry_of(report, 'unchanged')
    assert unchanged['decision'] == KEEP and unchanged['drift_p'] >= 0.05
    assert 'no drift' in unchanged['reason'] and unchanged['cost_difference'] is None

    corrupt = entry_of(report, 'corrupt')
    assert corrupt['decision'] == FAILED and corrupt['failed_stage'] == 'read'
    assert 'shift1.mcap' in corrupt['reason']

    # outputs complete, whole and loadable; nothing half-written left anywhere
    cells = out / 'cells'
    assert sorted(p.name for p in (cells / 'drifted').iterdir()) == sorted(
        ['cell_report.json', 'fitted.png', 'fitted.report.json', 'fitted.yaml', 'policy.npz',
         'shadow.png', 'live'])           # live: the files --apply set (fleet_apply.live_copy)
    from hrc_ros.core.mdp.policy import load_policy
    fitted = load_config(cells / 'drifted' / 'fitted.yaml')
    assert fitted.policy_hash == drifted['fit']['config_sha256']
    load_policy(cells / 'drifted' / 'policy.npz', fitted)
    for cell, decision in (('drifted', PROMOTE), ('unchanged', KEEP), ('corrupt', FAILED),
                           ('pomdp', PROMOTE)):
        written = json.loads((cells / cell / 'cell_report.json').read_text())
        assert written['decision'] == decision and written['cell'] == cell
    assert not list(out.rglob('*.tmp*'))
    markdown = (out / 'plant_report.md').read_text()
    for cell in ('drifted', 'unchanged', 'corrupt', 'pomdp'):
        assert f'| {cell} |' in markdown
    assert (out / 'plant_costs.png').stat().st_size > 1000


def test_apply_swaps_the_promoted_cell_live_and_a_cell_not_running_is_reported(plant_run):
    drifted = entry_of(plant_run['report'], 'drifted')
    assert plant_run['alive'], plant_run['logs']
    assert drifted['applied']['status'] == 'swapped', drifted['applied']
    assert len(plant_run['lives']['drifted']) == 1
    live, cell = plant_run['lives']['drifted'][0], plant_run['out'] / 'cells' / 'drifted'
    for name in ('fitted.yaml', 'policy.npz'):
        assert (live / name).read_bytes() == (cell / name).read_bytes(), name
    assert plant_run['new_policy'] in drifted['applied']['detail']
    assert 'applied' not in entry_of(plant_run['report'], 'unchanged')
    # independently of the applier: the node itself reports deciding with the new policy
    fitted_sha = drifted['fit']['config_sha256']
    assert any(v.get('policy_file') == plant_run['new_policy']
               and v.get('config_sha256') == fitted_sha for v in plant_run['seen']['drifted']), (
        plant_run['seen']['drifted'][-3:], plant_run['logs'])
    from hrc_ros.ros.fleet_apply import apply_promoted
    elsewhere = {**drifted, 'cell': 'elsewhere', 'namespace': '/fleet_nobody_here'}
    result = apply_promoted([elsewhere], timeout=5.0)['elsewhere']
    assert result['status'] == 'not running' and '/fleet_nobody_here/decision' in \
        result['detail']


def parameters_now(namespace: str, decision: list[str]) -> tuple:
    """(the decision node's parameters `decision`, the belief estimator's config) of the nodes
    in `namespace`, read through their parameter services; None for a node whose services do
    not show up or that does not answer."""
    from hrc_ros.ros.fleet_apply import Applier
    applier = Applier()
    try:
        answers = []
        for node, names in (('decision', decision), ('belief_estimator', ['config'])):
            client = applier.client(f'{namespace}/{node}')
            answers.append(None if client is None else applier.get(client, names))
        return tuple(answers)
    finally:
        applier.close()


def wait_answering(namespace: str, timeout: float = 120.0) -> None:
    """Until the decision node and the belief estimator in `namespace` answer their parameter
    services: --apply is for a running cell. Applied during their start, on a loaded machine the
    decision node did not answer for its selector within SET_TIMEOUT (10 s): it was still
    loading its policy (the quiet CI run of 2026-12-06 11:35)."""
    deadline = time.monotonic() + timeout
    while None in parameters_now(namespace, ['config']):
        assert time.monotonic() < deadline, f'{namespace}: the nodes never answered'


def test_apply_changes_nothing_on_a_node_of_another_selector_or_when_the_set_is_refused(
        tmp_path, ros_domain_id):
    """--apply against running nodes (processes): a node that runs another selector than the
    plant checked the cell with is `not applied`, nothing set; a set the decision node refuses
    (a policy.npz solved for another configuration) is refused whole, in one atomic set, so
    its configuration is not left staged, and the belief estimator's configuration goes back
    to what it ran."""
    import shutil
    from hrc_ros.core.paths import share_dir, shipped_config_path
    from hrc_ros.ros.fleet_apply import apply_promoted
    from hrc_ros.ros.processes import NodeProcesses
    params = tmp_path / 'params.yaml'
    params.write_text('/fleet_checks/decision:\n  ros__parameters:\n    selector: paper\n'
                      '    epoch_period: 0.5\n    stale_timeout: 1.0\n')
    folder = tmp_path / 'cells' / 'checks'
    folder.mkdir(parents=True)
    shutil.copyfile(shipped_config_path('fail_safe_unaware'), folder / 'fitted.yaml')
    shutil.copyfile(share_dir() / 'policies' / 'default.npz', folder / 'policy.npz')  # wrong
    entry = {'cell': 'checks', 'decision': 'promote', 'namespace': '/fleet_checks',
             'folder': str(folder), 'fit': {'config_sha256': 'x' * 64}}
    suite = NodeProcesses(tmp_path, [params])
    for node in ('decision_node', 'belief_estimator_node'):
        suite.start(node, remappings=[('__ns', '/fleet_checks')])
    try:
        wait_answering('/fleet_checks')
        other = apply_promoted([{**entry, 'selector': 'pomdp'}], timeout=5.0)['checks']
        refused = apply_promoted([{**entry, 'selector': 'paper'}], timeout=5.0)['checks']
        after = parameters_now('/fleet_checks', ['config', 'policy', 'selector'])
        dead = suite.dead()
    finally:
        suite.stop(10.0)
    assert not dead, suite.logs()
    assert other['status'] == 'not applied' and 'runs selector paper' in other['detail'], other
    assert refused['status'] == 'refused', refused
    assert 'policy refused' in refused['detail'] and 'was solved for configuration' in \
        refused['detail']
    assert after == ({'config': '', 'policy': '', 'selector': 'paper'}, {'config': ''})


def test_apply_night_after_night_and_a_set_the_node_refuses_at_the_boundary(tmp_path,
                                                                            ros_domain_id):
    """--apply against running nodes, from the same OUT night after night: the second
    night's files, written over the first's at the same paths, are swapped in too (the node
    compares parameter values: the same paths again were the set in use, and it kept the
    first night's pair, 'not verified'); a set the node takes and then refuses at the epoch
    boundary (a policy whose meta is right and whose arrays are not) is `refused` with the
    node's reason and the belief estimator's configuration goes back (it was left on the
    refused one)."""
    import shutil
    from hrc_ros.core.paths import share_dir, shipped_config_path
    from hrc_ros.ros.fleet_apply import apply_promoted
    from hrc_ros.ros.processes import NodeProcesses
    params = tmp_path / 'params.yaml'
    params.write_text('/fleet_nights/decision:\n  ros__parameters:\n    selector: paper\n'
                      '    epoch_period: 0.5\n    stale_timeout: 1.0\n')
    folder = tmp_path / 'cells' / 'nights'
    folder.mkdir(parents=True)
    entry = {'cell': 'nights', 'decision': 'promote', 'namespace': '/fleet_nights',
             'folder': str(folder), 'selector': 'paper'}

    def night(name: str, policy: Path) -> dict:
        shutil.copyfile(shipped_config_path(name), folder / 'fitted.yaml')
        shutil.copyfile(policy, folder / 'policy.npz')
        sha = load_config(folder / 'fitted.yaml').policy_hash
        return {**entry, 'fit': {'config_sha256': sha}}
    damaged = tmp_path / 'damaged.npz'
    with np.load(share_dir() / 'policies' / 'fail_safe_unaware.npz') as archive:
        arrays = {k: archive[k] for k in archive.files}
    arrays['policy'] = arrays['policy'].copy()
    arrays['policy'][7] = 99                   # no such action: only the full load sees it
    np.savez(damaged, **arrays)
    suite = NodeProcesses(tmp_path, [params])
    for node in ('decision_node', 'belief_estimator_node'):
        suite.start(node, remappings=[('__ns', '/fleet_nights')])
    try:
        wait_answering('/fleet_nights')
        first = apply_promoted([night('fail_safe_unaware',
                                      share_dir() / 'policies' / 'fail_safe_unaware.npz')],
                               timeout=20.0)['nights']
        second = apply_promoted([night('default', share_dir() / 'policies' / 'default.npz')],
                                timeout=20.0)['nights']
        lives = sorted((folder / 'live').iterdir(), key=lambda p: p.stat().st_mtime)
        refused = apply_promoted([night('fail_safe_unaware', damaged)], timeout=20.0)['nights']
        after = parameters_now('/fleet_nights', ['config', 'policy'])
        dead = suite.dead()
    finally:
        suite.stop(10.0)
    assert not dead, suite.logs()
    assert first['status'] == 'swapped', (first, suite.logs())
    assert second['status'] == 'swapped', (second, suite.logs())
    assert len(lives) == 2 and str(lives[1] / 'policy.npz') in second['detail']
    assert refused['status'] == 'refused', (refused, suite.logs())
    assert 'refused it at the epoch boundary' in refused['detail']
    assert "the belief estimator's configuration was set back" in refused['detail']
    night_two = {'config': str(lives[1] / 'fitted.yaml'), 'policy': str(lives[1] / 'policy.npz')}
    assert after == (night_two, {'config': night_two['config']})


def test_apply_reports_a_namespace_whose_decision_node_is_not_ours_and_goes_on(tmp_path,
                                                                               ros_domain_id):
    """A node named decision without a selector parameter (not an hrc_ros decision node) is
    `not applied` and the next cell is tried; the get-parameters service answers no value for
    an undeclared name, and a KeyError ended the whole --apply (no plant report written)."""
    import shutil
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from hrc_ros.core.paths import share_dir, shipped_config_path
    from hrc_ros.ros.fleet_apply import apply_promoted
    folder = tmp_path / 'cell'
    folder.mkdir()
    shutil.copyfile(shipped_config_path('default'), folder / 'fitted.yaml')
    shutil.copyfile(share_dir() / 'policies' / 'default.npz', folder / 'policy.npz')
    entry = {'decision': 'promote', 'folder': str(folder), 'selector': 'paper',
             'fit': {'config_sha256': 'x' * 64}}
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node('decision', namespace='/fleet_impostor', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    try:
        results = apply_promoted([{**entry, 'cell': 'impostor', 'namespace': '/fleet_impostor'},
                                  {**entry, 'cell': 'nobody', 'namespace': '/fleet_nobody'}],
                                 timeout=5.0)
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
        spinner.join(10.0)
    assert results['impostor']['status'] == 'not applied', results
    assert 'no selector parameter' in results['impostor']['detail']
    assert results['nobody']['status'] == 'not running', results


def test_a_pomdp_cell_is_solved_checked_with_its_selector_and_swapped_with_its_pomdp_policy(
        plant_run, small_cell):
    """The POMDP cell: both policies solved (the POMDP with the cell's settings), the shadow
    check run with the pomdp selector against the running POMDP policy its pomdp_policy names,
    and --apply sets config, pomdp_policy and policy: the node reports all three."""
    entry, files = entry_of(plant_run['report'], 'pomdp'), plant_run['files']['pomdp']
    assert entry['decision'] == PROMOTE and entry['drift']['drifted'], entry['reason']
    assert entry['selector'] == 'pomdp' and entry['shadow']['selector'] == 'pomdp'
    assert entry['cost_difference']['refits'] == 3         # the cell's own evaluate.refits
    assert set(entry['solve']) == {'mdp', 'pomdp'}
    folder = plant_run['out'] / 'cells' / 'pomdp'
    assert {'policy.npz', 'pomdp.npz', 'fitted.yaml'} <= {p.name for p in folder.iterdir()}
    from hrc_ros.core.pomdp.policy import load_pomdp_policy
    fitted = load_config(folder / 'fitted.yaml')
    assert (fitted.rho, fitted.sigma) == (1, 1)
    solved = load_pomdp_policy(folder / 'pomdp.npz', fitted)
    assert solved.meta['report']['rounds'] == 0 and solved.meta['report']['episodes'] == 10
    assert entry['applied']['status'] == 'swapped', entry['applied']
    assert files['pomdp'] in entry['applied']['detail']
    started = plant_run['pomdp_log']         # it ran the POMDP policy its cell names
    assert f'selector pomdp (POMDP policy {small_cell["pomdp"]})' in started
    assert any(v.get('policy_file') == files['policy']
               and v.get('pomdp_policy_file') == files['pomdp']
               and v.get('config_sha256') == entry['fit']['config_sha256']
               for v in plant_run['seen']['pomdp']), (plant_run['seen']['pomdp'][-3:],
                                                      plant_run['logs'])


def kill_me_once(marker: str, stage: str, cell: str) -> None:
    """In the worker: the first drift simulation task records its pid and waits to be
    killed; later calls (the retry) record theirs and go on."""
    if stage != 'drift_null':
        return
    with open(marker + '.calls', 'a') as calls:
        calls.write(f'{os.getpid()}\n')
    if os.path.exists(marker):
        return
    mine = f'{marker}.{os.getpid()}'
    with open(mine, 'w') as f:
        f.write(str(os.getpid()))
    try:
        os.link(mine, marker)       # the first of the tasks running side by side wins
    except FileExistsError:
        return
    time.sleep(60.0)                # the test kills this process before it wakes


def test_a_worker_killed_mid_task_is_retried_and_the_report_is_right(ray_session, plant_dir,
                                                                      plant_run, tmp_path):
    from ray import cloudpickle
    from hrc_ros.tools.fleet import Progress, run_plant
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    plant = load_plant(plant_dir / 'plant.yaml')
    plant = replace(plant, cells=tuple(c for c in plant.cells if c.name == 'unchanged'))
    marker = str(tmp_path / 'victim.pid')
    killed = []

    def killer():
        deadline = time.monotonic() + 60
        while not os.path.exists(marker) and time.monotonic() < deadline:
            time.sleep(0.05)
        pid = int(Path(marker).read_text())
        os.kill(pid, signal.SIGKILL)
        killed.append(pid)
    thread = threading.Thread(target=killer, daemon=True)
    thread.start()
    report = run_plant(plant, tmp_path / 'out', hook=partial(kill_me_once, marker),
                       progress=Progress(quiet=True))
    thread.join(5.0)
    calls = [int(line) for line in Path(marker + '.calls').read_text().split()]
    assert killed and killed[0] in calls
    assert not Path(f'/proc/{killed[0]}').exists() or \
        Path(f'/proc/{killed[0]}/stat').read_text().split()[2] == 'Z'
    assert calls.count(killed[0]) == 1 and len(calls) == 5      # 4 chunks, one run twice
    (entry,) = report['cells']
    reference = entry_of(plant_run['report'], 'unchanged')
    assert entry['decision'] == KEEP, entry['reason']
    assert entry['drift_p'] == reference['drift_p']
    assert entry['drift']['statistic'] == reference['drift']['statistic']
    # the report says what Ray redid: the killed task ran twice, on two workers
    (retried,) = entry['retries']
    assert retried['stage'].startswith('null.') and retried['attempts'] == 2
    assert killed[0] in [w['pid'] for w in retried['workers']]
    assert report['retried_tasks'] == 1 and report['lost_nodes'] == []


DECIDE_RIGHT = """\
plant: decide_right
defaults:
  policy: {policy}
  run: always
  drift: {{simulations: 9}}
  fit: {{bootstrap: 0}}
cells:
  - name: unchanged_always
    seed: 14
    generate: {{world: {{}}, episodes: 20, epochs: 50, seed: 1014}}
  - name: eager_close
    seed: 3
    generate: {{world: {eager_close}, episodes: 80, epochs: 50, seed: 3}}
"""
# a whole plant on the defaults (ten refits a cell), in this process: 80 s on a quiet machine
# of 2026-12-07, beyond the suite's 300 s at load 13 there (the worker ended, "node down");
# it gets the plant's time, as the --apply run does
@pytest.mark.timeout(PLANT_TIMEOUT)
def test_a_truly_better_cell_is_promoted_and_a_cell_of_the_default_world_kept(
        ray_session, tmp_path, policy_path):
    """The issue's two cases. A cell of the default's people, fitted from its 1000 epochs: the
    refit is cheaper in the world fitted from those same epochs, with 95% confidence over the
    episodes (the in-sample interval alone promoted it), and the refits show that as the
    fit's optimism: kept. A cell whose people accept readily and drift closer (the default's
    regret 3.01 per episode), 4000 epochs of them (at 2000 the check's 95% interval was still
    +-2.3 per episode wide): promoted, although its new policy refuses more requests (a fixed
    guard on refused requests kept it, and would keep the world's optimum itself), since the
    cost it minimises prices the refusals. Seeded: the figures are the same every run."""
    from hrc_ros.tools.fleet import Progress, run_plant
    (tmp_path / 'plant.yaml').write_text(DECIDE_RIGHT.format(
        policy=policy_path, eager_close=json.dumps(EAGER_CLOSE)))
    report = run_plant(load_plant(tmp_path / 'plant.yaml'), tmp_path / 'out',
                       progress=Progress(quiet=True))
    unchanged, eager = report['cells']
    cost = unchanged['cost_difference']
    assert cost['in_sample'] + cost['in_sample_half_width'] < 0      # in-sample: 'cheaper'
    assert unchanged['decision'] == KEEP, unchanged['reason']
    assert cost['high'] >= 0 and cost['optimism'] < 0
    assert 'not cheaper with 95% confidence' in unchanged['reason']
    assert eager['decision'] == PROMOTE, eager['reason']
    assert eager['cost_difference']['high'] < 0
    assert eager['refused_requests']['mean'] > 0          # more refused, priced by the cost
    markdown = (tmp_path / 'out' / 'plant_report.md').read_text()
    assert '| unchanged_always | /unchanged_always | always | **keep** |' in markdown
    assert '| eager_close | /eager_close | always | **promote** |' in markdown


class Stream:
    def __init__(self, tty: bool):
        self.tty, self.text = tty, ''

    def isatty(self):
        return self.tty

    def write(self, text):
        self.text += text

    def flush(self):
        pass


def test_progress_redraws_one_line_on_a_terminal_and_logs_changes_otherwise(tmp_path):
    from hrc_ros.tools.fleet import Progress
    p = pipeline_of(tmp_path)
    p.start()
    terminal, log = Stream(True), Stream(False)
    for stream in (terminal, log):
        bar = Progress(stream)
        bar([p])
        bar([p])                       # no change: the log gets no second line
        p.stage = 'drift'
        bar([p])
        bar.close()
        p.stage = 'read'
    assert terminal.text.count('\r') == 3 and terminal.text.endswith('\n')
    assert '0/1 cells' in terminal.text and 'a: drift' in terminal.text
    assert log.text.splitlines() == ['hrc-fleet: [0/1] a: read', 'hrc-fleet: [0/1] a: drift']


@pytest.mark.parametrize('cpus', [1, 2])
def test_a_ray_task_keeps_the_kernels_to_the_cpus_it_was_given(cpus, monkeypatch):
    """core.parallel's kernels set numba's thread count themselves (every core in the auto
    mode), which undid the task's numba.set_num_threads: two one-CPU tasks on two cores ran
    two threads each. The task's CPUs now bound the kernels' threads, in the auto mode (the
    product's default; the suite's own is serial, conftest.py)."""
    import numba

    from hrc_ros.core import parallel
    from hrc_ros.tools import fleet

    class Context:
        def get_assigned_resources(self):
            return {'CPU': float(cpus)}

    class FakeRay:
        def get_runtime_context(self):
            return Context()

    monkeypatch.delenv(parallel.ENV, raising=False)
    threads = numba.get_num_threads()
    try:
        parallel.set_mode(None)
        fleet._threads_as_assigned(FakeRay())
        assert parallel.current_mode() == parallel.AUTO
        assert parallel.machine_threads() <= cpus
        kernel = parallel.ParallelKernel('probe', lambda: numba.get_num_threads(),
                                         lambda: 1)
        # a kernel that runs parallel gets no more threads than the task's CPUs
        used = max(kernel() for _ in range(8))
        assert used <= cpus
    finally:
        parallel.limit_threads(None)
        parallel.set_mode(None)
        numba.set_num_threads(threads)


# -- the engine's edges: a cluster that cannot be joined, Ctrl-C ------------------------------
def fleet_process(args: list[str], env: dict | None = None, **kwargs):
    """hrc-fleet in a new session (its own process group, as a terminal's foreground job),
    SIGINT at Python's default (a suite started as a background job ignores it)."""
    import subprocess

    def default_sigint():
        signal.signal(signal.SIGINT, signal.SIG_DFL)
    return subprocess.Popen([sys.executable, '-m', 'hrc_ros.tools.fleet', 'run', *args],
                            cwd=REPO, env={**os.environ, **(env or {})},
                            start_new_session=True, preexec_fn=default_sigint,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kwargs)


def session_processes(sid: int) -> list[tuple[int, str]]:
    """The live processes of session `sid` (Ray's agents stay in it when orphaned)."""
    out = []
    for entry in Path('/proc').iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / 'stat').read_text()
            except OSError:
                continue
            fields = stat.rsplit(')', 1)[1].split()
            if int(fields[3]) == sid and fields[0] not in ('Z', 'X'):
                out.append((int(entry.name), stat.split('(', 1)[1].rsplit(')', 1)[0]))
    return out


def test_a_cluster_that_refuses_the_connection_is_one_line_in_seconds_and_leaves_no_out(
        tmp_path):
    """`--address 127.0.0.1:1`: Ray itself retried it for 824 s with 60 warnings naming the
    address it resolved to, and left an empty --out."""
    out = tmp_path / 'out'
    t0 = time.monotonic()
    run = fleet_process([str(REPO / 'config' / 'plant_example.yaml'), '--out', str(out),
                         '--address', '127.0.0.1:1'])
    stdout, stderr = run.communicate(timeout=60)
    assert run.returncode == 2, (stdout, stderr)
    assert time.monotonic() - t0 < 30
    (line,) = stderr.strip().splitlines()
    assert line.startswith('hrc-fleet: error: cannot join the Ray cluster at 127.0.0.1:1')
    assert 'connection refused' in line and not out.exists()


def test_a_ray_client_address_is_pinged_once_and_a_port_of_another_kind_refused_in_seconds(
        ray_session, tmp_path):
    """`--address ray://host:port` whose port answers TCP but is no Ray Client server (here a
    socket that listens and never speaks): Ray's client retried 30 s and said only 'ray client
    connection timeout' (without grpcio installed: a ModuleNotFoundError traceback). One line
    naming the address and the cause, in seconds, and no --out. A real Ray Client server (Ray's
    own, serving the session's cluster) passes the same ping."""
    import socket

    from ray.util.client.server.server import serve

    from hrc_ros.tools import fleet_ray
    silent = socket.create_server(('127.0.0.1', 0))
    try:
        address = f'ray://127.0.0.1:{silent.getsockname()[1]}'
        out = tmp_path / 'out'
        t0 = time.monotonic()
        run = fleet_process([str(REPO / 'config' / 'plant_example.yaml'), '--out', str(out),
                             '--address', address])
        stdout, stderr = run.communicate(timeout=60)
        assert run.returncode == 2, (stdout, stderr)
        assert time.monotonic() - t0 < 30
        (line,) = stderr.strip().splitlines()
        assert line.startswith(f'hrc-fleet: error: cannot join the Ray cluster at {address}')
        assert 'no gRPC server within 5 s' in line and not out.exists()
    finally:
        silent.close()
    free = socket.create_server(('127.0.0.1', 0))
    port = free.getsockname()[1]
    free.close()
    server = serve('127.0.0.1', port)
    try:
        assert fleet_ray.check_address(f'ray://127.0.0.1:{port}') == f'127.0.0.1:{port}'
    finally:
        server.stop(0)


def test_a_cluster_that_refuses_the_token_is_named_as_such(ray_session, tmp_path):
    """A driver without the cluster's token: Ray said only 'Failed to connect' after 20 s of
    warnings; the line says the token was refused. The cluster is the session's own (Ray
    starts an embedded cluster with token authentication unless RAY_AUTH_MODE says not)."""
    from ray._private.authentication.authentication_utils import is_token_auth_enabled
    if not is_token_auth_enabled():
        pytest.skip('the session\'s Ray runs without token authentication (RAY_AUTH_MODE)')
    address = ray_session.get_runtime_context().gcs_address
    out = tmp_path / 'out'
    run = fleet_process([str(REPO / 'config' / 'plant_example.yaml'), '--out', str(out),
                         '--address', address],
                        env={'RAY_AUTH_MODE': 'token', 'RAY_AUTH_TOKEN': 'x' * 64})
    stdout, stderr = run.communicate(timeout=60)
    assert run.returncode == 2, (stdout, stderr)
    (line,) = stderr.strip().splitlines()
    assert f'cannot join the Ray cluster at {address}' in line
    assert "refused this driver's authentication token" in line and not out.exists()


def test_any_error_of_ray_joining_a_cluster_is_one_line(monkeypatch):
    """Ray's own errors on joining (AuthenticationError, RpcError: RayError, not
    ConnectionError or RuntimeError) went through as a traceback and left OUT behind; every
    error of ray.init on an address the check passed is now the one line (ToolError)."""
    import ray
    import ray.exceptions

    from hrc_ros.tools import fleet
    from hrc_ros.tools.common import ToolError

    def refuse(**kwargs):
        raise ray.exceptions.AuthenticationError('the token does not match the cluster\'s')
    monkeypatch.setattr(ray, 'is_initialized', lambda: False)
    monkeypatch.setattr(ray, 'init', refuse)
    with pytest.raises(ToolError) as refused:
        fleet.start_ray('10.0.0.9:6379', None, None, checked=True)
    line = str(refused.value)
    assert line.startswith('cannot join the Ray cluster at 10.0.0.9:6379')
    assert 'AuthenticationError' in line and 'does not match' in line and '\n' not in line


# a process of the embedded cluster that marks the moment: its raylet (the cluster starting),
# a Ray worker running a stage (Ray names a worker by the task it runs)
MOMENTS = {'start': lambda name: name == 'raylet',
           'stage': lambda name: name.startswith('ray::stage_task')}


@pytest.mark.parametrize('moment', MOMENTS)
def test_ctrl_c_on_an_embedded_cluster_exits_130_and_leaves_no_process(tmp_path, moment):
    """Ctrl-C (SIGINT to the foreground process group) as the embedded cluster starts, and
    while a stage runs on it: exit 130 and one line, no process of the cluster left. Before,
    a KeyboardInterrupt raised inside Ray's calls left Ray's GCS, dashboard and agents running
    (3 runs in 4) and the driver died with SIGSEGV after 'interrupted' (1 in 4); during the
    stages it did too (one run in two at 8 s, in the issue). Ray's own output goes to
    OUT/ray.log."""
    (tmp_path / 'plant.yaml').write_text(
        'cells:\n  - name: a\n    run: always\n    generate: {world: {}, episodes: 20, '
        'epochs: 50, seed: 3}\n')
    out = tmp_path / 'out'
    run = fleet_process([str(tmp_path / 'plant.yaml'), '--out', str(out), '--num-cpus', '1'])
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and run.poll() is None and not any(
            MOMENTS[moment](name) for _, name in session_processes(run.pid)):
        time.sleep(0.05)
    assert run.poll() is None, run.communicate()
    os.killpg(run.pid, signal.SIGINT)
    stdout, stderr = run.communicate(timeout=90)
    assert run.returncode == 130, (run.returncode, stderr)
    assert stderr.strip().splitlines()[-1] == 'hrc-fleet: interrupted', stderr
    deadline = time.monotonic() + 3          # those it ended as it exited: reaped by now
    while session_processes(run.pid) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert session_processes(run.pid) == []
    assert (out / 'ray.log').is_file() and 'WARNING' not in stdout + stderr
