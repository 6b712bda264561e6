"""A plant's generated cell (hrc-fleet `generate:`, docs/FLEET.md): its people are the
world's, and its cache follows what the recordings depend on.

- a world with a person prior (observation.prior) records people drawn from that prior, as
  hrc-evaluate --true-config draws them (`episodes_of(..., prior=)`), not uniform ones;
- the cache's key changes when the generator, the settings or a world file's contents change,
  and not otherwise, and follows the shipped policy a cell without one runs;
- generated recordings carry the tasks waiting, and cuts (the drift window's, the fit's
  window) cut them too, so a queue base's stream can be fitted from them; fit.prior refuses at
  read recordings in which no episode starts (review of the plant's fit.prior / fit.stream).
"""

from __future__ import annotations

import numpy as np
import pytest

from hrc_ros.core.mdp.policy import default_policy_path, load_policy
from hrc_ros.core.model import HRCModel
from hrc_ros.core.plant import spec as plant_spec
from hrc_ros.core.plant import stages
from hrc_ros.core.plant.spec import load_plant
from hrc_ros.core.study.evaluation import BatchSimulator, episodes_of

# nearly everyone unmotivated and calm (h = 3*em + ea = 0)
PRIOR = [0.92] + [0.01] * 8


@pytest.fixture(scope='module')
def policy(default_config):
    return load_policy(default_policy_path(default_config), default_config)


def settings(world: dict) -> dict:
    return {'world': world, 'episodes': 8, 'epochs': 30, 'seed': 3, 'explore': 0.2}


def test_generated_people_are_drawn_from_the_worlds_prior(default_config, policy):
    world_overrides = {'observation': {'prior': PRIOR}}
    _, text = stages.generate(default_config, policy, settings(world_overrides), 'paper')

    world = HRCModel(default_config.with_overrides(world_overrides))
    model = HRCModel(default_config)
    scenarios, seeds = episodes_of(model, 'random', 8, 30, 3, prior=PRIOR)
    people = np.array([s.initial_state[:2] for s in scenarios])
    assert (people == 0).all(axis=1).sum() >= 5     # the prior's people, not uniform ones
    result = BatchSimulator(model, policy, world=world).run(scenarios, seeds, 'paper',
                                                            explore=0.2, record=True)
    assert text == stages.recordings_csv(result.recordings(world))

    # the same settings without the prior: uniform people, other recordings
    _, uniform = stages.generate(default_config, policy, settings({}), 'paper')
    assert uniform != text


def test_generate_key_follows_the_generator_and_the_world_files(tmp_path, monkeypatch):
    world = tmp_path / 'world.yaml'
    world.write_text('model: {p_accept: [0.05, 0.35, 0.7]}\n')
    plant = tmp_path / 'plant.yaml'
    plant.write_text('cells:\n  - name: a\n    generate: {world: world.yaml, episodes: 4, '
                     'epochs: 20, seed: 1}\n')
    key = load_plant(plant).cells[0].generate_key()
    assert load_plant(plant).cells[0].generate_key() == key      # stable
    world.write_text('model: {p_accept: [0.05, 0.35, 0.8]}\n')
    edited = load_plant(plant).cells[0].generate_key()
    assert edited != key
    monkeypatch.setattr(plant_spec, 'GENERATOR', plant_spec.GENERATOR + 1)
    assert load_plant(plant).cells[0].generate_key() not in (key, edited)


def test_generated_recordings_carry_the_tasks_waiting_and_a_queue_base_fits_their_stream(
        tmp_path):
    """A generated cell on a queue base (stream.queue) records the tasks waiting, so that
    fit.stream can count the queue's releases from it (it failed the cell at read: no
    `queued`); windows and cuts that cut an episode cut its tasks waiting with it (a cut
    raised a broadcast error)."""
    from hrc_ros.core.config import load_config
    from hrc_ros.core.learning.stream import fit_stream_for
    from hrc_ros.core.paths import shipped_config_path
    base = load_config(shipped_config_path('stream_queue'))
    policy = load_policy(default_policy_path(base), base)
    _, text = stages.generate(base, policy, {'world': {}, 'episodes': 5, 'epochs': 41,
                                             'seed': 4, 'explore': 0.2}, 'paper')
    assert text.splitlines()[0].endswith(',queued')
    path = tmp_path / 'q.csv'
    path.write_text(text)
    facts, data = stages.read([str(path)], base.rho, base.sigma, '/', 100, 150, base)
    assert facts['epochs'] == 150 and sum(len(r) for r in data['recordings']) == 150
    parts = [stages.span(data['recordings'], 0, 75), stages.span(data['recordings'], 75, 150)]
    for r in data['recordings'] + [r for part in parts for r in part]:
        assert len(r.queued) == len(r)
    assert {len(parts[0][-1]), len(parts[1][0])} != {41}         # an episode was cut
    for part in parts:
        fit_stream_for(part, base, bootstrap=0)                   # no error


def test_fit_prior_refuses_recordings_in_which_no_episode_starts(tmp_path, default_config,
                                                                policy):
    """fit.prior fits where people start, so recordings in which no episode starts at epoch 1
    (here: the fit's window cuts the one long run) fail the cell when they are read, with
    one line naming fit.prior, not after the fit."""
    _, text = stages.generate(default_config, policy, {'world': {}, 'episodes': 1,
                                                       'epochs': 200, 'seed': 2,
                                                       'explore': 0.2}, 'paper')
    path = tmp_path / 'long.csv'
    path.write_text(text)
    args = ([str(path)], default_config.rho, default_config.sigma, '/', 100)
    stages.read(*args, None, None, True)                          # the whole run: fine
    with pytest.raises(stages.CellError, match='fit.prior: no episode in the recordings '
                                               'starts at epoch 1'):
        stages.read(*args, 100, None, True)                       # its last 100 epochs


def test_the_cache_follows_the_shipped_policy_a_cell_without_one_runs(tmp_path, monkeypatch):
    """`policy: null` runs the shipped policy of its base: the cache's key follows that file
    (it hashed the None)."""
    plant = tmp_path / 'plant.yaml'
    plant.write_text('cells:\n  - name: a\n    generate: {world: {}, episodes: 4, epochs: 20, '
                     'seed: 1}\n')
    cell = load_plant(plant).cells[0]
    key = cell.generate_key()
    other = tmp_path / 'other.npz'
    other.write_bytes(b'not the shipped policy')
    monkeypatch.setattr(plant_spec, '_shipped_policy', lambda base: str(other))
    assert cell.generate_key() != key
