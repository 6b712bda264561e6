"""A plant's generated cell (hrc-fleet `generate:`, docs/FLEET.md): its people are the
world's, and its cache follows what the recordings depend on.

- a world with a person prior (observation.prior) records people drawn from that prior, as
  hrc-evaluate --true-config draws them (`episodes_of(..., prior=)`), not uniform ones;
- the cache's key changes when the generator, the settings or a world file's contents change,
  and not otherwise.
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
