"""Solver benchmark: wall time and peak memory to a converged policy, against mdptoolbox.

    python bench/solve_bench.py                 # paper size, rho = sigma = 3 and 4, mdptoolbox
    python bench/solve_bench.py --sizes 2 --skip-mdptoolbox

Every measurement runs in its own subprocess so that its peak RSS (ru_maxrss) is its own.

- hrc_ros: model construction + value iteration to eta (default 1e-6) with
  `hrc_ros.core.mdp.solver`.
  The numba kernels are compiled (or loaded from numba's on-disk cache) before the clock
  starts; that one-off time is reported separately as `jit`.
- mdptoolbox-hiive `ValueIteration` on the 8 explicit N x N CSR matrices built from the same
  model rule by rule (`HRCModel.sparse_matrices`, timed separately: it is not part of a
  solve). Its constructor calls `_boundIter`, an O(S^2 A) bound on the sweep count that never
  finishes at this size, so the benchmark subclasses it with `_boundIter` bypassed
  (max_iter = 100000). Its own stopping rule is the span of V_{t+1} - V_t against
  epsilon (1 - gamma) / gamma; the benchmark stops it instead with hrc_ros's rule,
  max |V_{t+1} - V_t| < eta, by running its `_bellmanOperator` sweep by sweep, so both
  solvers reach the same tolerance with the same operator. The policies are then compared
  state by state; a difference counts as a tie when the two actions' Q values (from the
  converged V) are within 1e-6 * max(1, |V|).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

TIE_TOLERANCE = 1e-6


def _config(rho: int, sigma: int, eta: float):
    from hrc_ros.core.config import load_config
    return load_config(REPO / 'config' / 'default.yaml',
                       overrides={'model': {'rho': rho, 'sigma': sigma},
                                  'solver': {'eta': eta}})


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def child_hrc(rho: int, sigma: int, eta: float, policy_out: str | None) -> dict:
    t = time.perf_counter()
    from hrc_ros.core.model import HRCModel
    from hrc_ros.core.mdp.solver import solve
    solve(HRCModel(_config(1, 1, 1e-3)), sweeps=2)  # compile or load the numba kernels
    jit = time.perf_counter() - t
    cfg = _config(rho, sigma, eta)
    t0 = time.perf_counter()
    model = HRCModel(cfg)
    result = solve(model)
    total = time.perf_counter() - t0
    if policy_out:
        np.savez(policy_out, policy=result.policy, value=result.value)
    return {'solver': 'hrc_ros', 'rho': rho, 'sigma': sigma, 'states': model.n_states,
            'seconds': total, 'sweeps': result.iterations, 'residual': result.residual,
            'per_sweep_ms': 1e3 * result.timings['iterate'] / result.iterations,
            'peak_mb': _peak_mb(), 'jit_s': jit}


def child_mdptoolbox(rho: int, sigma: int, eta: float, policy_out: str) -> dict:
    from hiive.mdptoolbox.mdp import ValueIteration

    from hrc_ros.core.model import ACTIONS, HRCModel

    class UnboundedValueIteration(ValueIteration):
        def _boundIter(self, epsilon):  # noqa: N802 - the library's name
            self.max_iter = 100_000  # the O(S^2 A) bound never finishes at this size

    model = HRCModel(_config(rho, sigma, eta))
    t0 = time.perf_counter()
    matrices = model.sparse_matrices()
    states = np.stack(np.unravel_index(np.arange(model.n_states), model.dims), axis=-1)
    reward = np.stack([-model.cost(states, a) for a in range(len(ACTIONS))], axis=1)
    build = time.perf_counter() - t0
    nnz = sum(m.nnz for m in matrices)
    t1 = time.perf_counter()
    vi = UnboundedValueIteration(matrices, reward, model.gamma, skip_check=True)
    sweeps = 0
    while True:
        previous = vi.V
        vi.policy, vi.V = vi._bellmanOperator()
        sweeps += 1
        residual = float(np.max(np.abs(vi.V - previous)))
        if residual < eta:
            break
    seconds = time.perf_counter() - t1
    np.savez(policy_out, policy=np.asarray(vi.policy, dtype=np.int8), value=vi.V)
    return {'solver': 'mdptoolbox', 'rho': rho, 'sigma': sigma, 'states': model.n_states,
            'seconds': seconds, 'sweeps': sweeps, 'residual': residual,
            'per_sweep_ms': 1e3 * seconds / sweeps, 'peak_mb': _peak_mb(),
            'matrix_build_s': build, 'nnz': int(nnz)}


def run_child(kind: str, rho: int, sigma: int, eta: float, policy_out: str | None) -> dict:
    cmd = [sys.executable, __file__, '--child', kind, str(rho), str(sigma), str(eta),
           policy_out or '']
    proc = subprocess.run(cmd, capture_output=True, text=True, env=os.environ.copy())
    if proc.returncode != 0:
        raise SystemExit(f'{kind} rho=sigma={rho} failed:\n{proc.stderr}')
    return json.loads(proc.stdout.strip().splitlines()[-1])


def compare_policies(ours_path: str, theirs_path: str, rho: int, sigma: int,
                     eta: float) -> dict:
    from hrc_ros.core.model import HRCModel
    from hrc_ros.core.mdp.solver import FactoredBellman
    ours = np.load(ours_path)
    theirs = np.load(theirs_path)
    differ = np.flatnonzero(ours['policy'] != theirs['policy'])
    q = FactoredBellman(HRCModel(_config(rho, sigma, eta))).q(ours['value'])
    qa = q[ours['policy'][differ], differ]
    qb = q[theirs['policy'][differ], differ]
    ties = np.abs(qa - qb) <= TIE_TOLERANCE * np.maximum(1.0, np.abs(qa))
    return {'states': int(ours['policy'].size), 'differ': int(differ.size),
            'differ_not_tie': int((~ties).sum()),
            'max_value_gap': float(np.max(np.abs(ours['value'] - theirs['value'])))}


def main() -> int:
    if len(sys.argv) > 1 and sys.argv[1] == '--child':
        kind, rho, sigma, eta, out = sys.argv[2:7]
        fn = child_hrc if kind == 'hrc' else child_mdptoolbox
        print(json.dumps(fn(int(rho), int(sigma), float(eta), out or None)))
        return 0
    parser = argparse.ArgumentParser(description=' '.join(__doc__.split('\n\n')[0].split()))
    parser.add_argument('--sizes', default='2,3,4', help='rho = sigma values (default 2,3,4)')
    parser.add_argument('--eta', type=float, default=1e-6)
    parser.add_argument('--skip-mdptoolbox', action='store_true')
    parser.add_argument('--json', help='also write the results here')
    args = parser.parse_args()
    sizes = [int(s) for s in args.sizes.split(',')]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for size in sizes:
            ours = os.path.join(tmp, f'hrc_{size}.npz')
            row = run_child('hrc', size, size, args.eta, ours)
            rows.append(row)
            print(f'hrc_ros     rho=sigma={size}: {row["states"]:>10,} states  '
                  f'{row["seconds"]:7.2f} s  {row["sweeps"]} sweeps '
                  f'({row["per_sweep_ms"]:.2f} ms each)  peak {row["peak_mb"]:.0f} MB  '
                  f'(numba jit/cache load {row["jit_s"]:.1f} s, not counted)', flush=True)
            if size == 2 and not args.skip_mdptoolbox:
                theirs = os.path.join(tmp, 'mdptoolbox.npz')
                ref = run_child('mdptoolbox', size, size, args.eta, theirs)
                rows.append(ref)
                print(f'mdptoolbox  rho=sigma={size}: {ref["states"]:>10,} states  '
                      f'{ref["seconds"]:7.2f} s  {ref["sweeps"]} sweeps '
                      f'({ref["per_sweep_ms"]:.2f} ms each)  peak {ref["peak_mb"]:.0f} MB  '
                      f'(explicit matrices: {ref["nnz"]:,} nonzeros, built in '
                      f'{ref["matrix_build_s"]:.1f} s, not counted)', flush=True)
                cmp = compare_policies(ours, theirs, size, size, args.eta)
                ref['comparison'] = cmp
                print(f'speed-up (same tolerance, same machine): '
                      f'{ref["seconds"] / row["seconds"]:.1f}x total, '
                      f'{ref["per_sweep_ms"] / row["per_sweep_ms"]:.1f}x per sweep')
                print(f'policies: {cmp["differ"]} of {cmp["states"]:,} states differ, '
                      f'{cmp["differ_not_tie"]} of them not ties; '
                      f'max |V_hrc - V_mdptoolbox| = {cmp["max_value_gap"]:.2e}')
    print('targets: paper size >= 10x mdptoolbox (2 s at most), peak < 600 MB; '
          'rho = sigma = 4 < 60 s and < 8 GB')
    print(f'reproduce: python bench/solve_bench.py --sizes {args.sizes}'
          + (' --skip-mdptoolbox' if args.skip_mdptoolbox else ''))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == '__main__':
    sys.exit(main())
