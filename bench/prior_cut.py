"""Whether the pieces cut from episodes should inform the person prior (hrc-fit --prior).

    .venv/bin/python bench/prior_cut.py [--seeds 10] [--episodes 400] [--every 10]

A world whose people start from a known non-uniform prior (the default configuration with
PRIOR) is recorded, `--episodes` episodes of 50 epochs per seed under the shipped policy with
20% explored actions, and one epoch in every `--every` is left out (a gap: the episode is cut
there, as at a transition the model cannot produce). Each seed's recordings are fitted three
ways, paired (the same recordings):

- `split` (hrc-fit --prior): the prior from the episodes' starts at epoch 1 only, the cut
  pieces from their own nuisance distribution;
- `shared`: every segment start read as a person's start (one distribution for all, as the
  nuisance pi is without --prior);
- `uncut`: the same recordings without the gaps (the best the data allow).

Prints the total variation distance of each fitted prior from PRIOR per seed, their means
and the paired differences with 95% intervals (t, over seeds).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np
from scipy import stats as st

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hrc_ros.core.config import Config, load_config, validate  # noqa: E402
from hrc_ros.core.learning import fit  # noqa: E402
from hrc_ros.core.learning.recordings import Recording  # noqa: E402
from hrc_ros.core.mdp.policy import load_policy  # noqa: E402
from hrc_ros.core.model import HRCModel  # noqa: E402
from hrc_ros.core.study.evaluation import BatchSimulator, random_scenarios  # noqa: E402

PRIOR = np.array([0.30, 0.04, 0.06, 0.10, 0.20, 0.05, 0.03, 0.07, 0.15])


def with_gaps(recording: Recording, every: int) -> Recording:
    keep = np.arange(len(recording)) % every != every - 1
    return dataclasses.replace(recording, **{
        f.name: getattr(recording, f.name)[keep] for f in dataclasses.fields(recording)
        if isinstance(getattr(recording, f.name), np.ndarray)})


def interval(values) -> str:
    values = np.asarray(values)
    half = st.t.ppf(0.975, len(values) - 1) * values.std(ddof=1) / np.sqrt(len(values))
    return f'{values.mean():+.4f} [{values.mean() - half:+.4f}, {values.mean() + half:+.4f}]'


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    parser.add_argument('--seeds', type=int, default=10)
    parser.add_argument('--episodes', type=int, default=400)
    parser.add_argument('--every', type=int, default=10)
    args = parser.parse_args(argv)
    base = load_config(ROOT / 'config' / 'default.yaml')
    data = dict(base.data)
    data['observation'] = dict(data['observation'], prior=PRIOR.tolist())
    world = Config(validate(data), 'default.yaml with PRIOR')
    model = HRCModel(world)
    policy = load_policy(ROOT / 'policies' / 'default.npz', base).policy
    print(f'prior_cut: {args.seeds} seeds x {args.episodes} episodes of 50 epochs, one epoch '
          f'in {args.every} left out; command: .venv/bin/python bench/prior_cut.py --seeds '
          f'{args.seeds} --episodes {args.episodes} --every {args.every}')
    errors = {'split': [], 'shared': [], 'uncut': []}
    for seed in range(args.seeds):
        scenarios = random_scenarios(model, args.episodes, 50, seed=100 + seed, prior=PRIOR)
        run = BatchSimulator(model, policy).run(
            scenarios, [[100 + seed, e] for e in range(args.episodes)], explore=0.2,
            record=True)
        recordings = run.recordings(model)
        cut = fit.prepare([with_gaps(r, args.every) for r in recordings])
        shared = dataclasses.replace(cut, seg_true_start=np.ones(cut.segments, dtype=bool))
        shared.__dict__.pop('_kinds', None)
        fits = {'split': cut, 'shared': shared, 'uncut': fit.prepare(recordings)}
        row = []
        for name, prepared in fits.items():
            result = fit.fit(prepared, base, n_init=1, bootstrap=0, prior=True)
            errors[name].append(0.5 * np.abs(result.params.pi - PRIOR).sum())
            row.append(f'{name} {errors[name][-1]:.4f}')
        print(f'seed {seed}: {cut.segments} segments, {int(cut.true_starts.sum())} episode '
              f'starts; total variation from the truth: ' + ', '.join(row))
    print('mean total variation: ' + ', '.join(f'{k} {np.mean(v):.4f}'
                                              for k, v in errors.items()))
    split, shared, uncut = (np.array(errors[k]) for k in ('split', 'shared', 'uncut'))
    print(f'shared - split: {interval(shared - split)}')
    print(f'split - uncut:  {interval(split - uncut)}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
