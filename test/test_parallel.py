"""The load-robust parallel kernels (core.parallel): which variant a call runs, the override,
and that the variants compute the same results for every parallel kernel of core/."""

import numpy as np
import pytest

from hrc_ros.core import parallel
from hrc_ros.core.parallel import ParallelKernel

MACHINE_THREADS = parallel.machine_threads


class Clock:
    """A clock the fake kernels advance by their cost, so the choice is deterministic."""

    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


def fake(costs: dict):
    """A kernel whose variants only record that they ran and cost costs[variant] seconds per
    unit of their argument."""
    clock = Clock()
    ran = []

    def variant(name):
        def run(x):
            ran.append(name)
            clock.now += costs[name] * x
            return x * 2
        return run
    return ParallelKernel('fake', variant('parallel'), variant('serial'), clock), ran, costs


@pytest.fixture(autouse=True)
def auto_mode(monkeypatch):
    monkeypatch.delenv(parallel.ENV, raising=False)
    monkeypatch.setattr(parallel, 'machine_threads', lambda: 2)
    parallel.set_mode(None)
    yield
    parallel.set_mode(None)


def test_auto_runs_the_faster_variant_and_probes_the_other_within_its_budget():
    kernel, ran, costs = fake({'parallel': 0.050, 'serial': 0.005})  # a busy machine
    for _ in range(1000):
        assert kernel(3) == 6
    assert ran[:2] == ['serial', 'parallel']       # each timed once, serial first
    slow = ran[4:].count('parallel')
    # probing costs at most about 1 / PROBE_RATIO of the run time
    assert 0 < slow * costs['parallel'] <= 1.5 * sum(costs[v] for v in ran) / parallel.PROBE_RATIO
    assert ran[-20:].count('serial') >= 19


def test_auto_follows_a_load_that_goes_and_comes():
    kernel, ran, costs = fake({'parallel': 0.050, 'serial': 0.005})
    for _ in range(200):
        kernel(1)
    costs['parallel'] = 0.003           # the other process ended: parallel is faster now
    n = len(ran)
    for _ in range(2000):
        kernel(1)
    switched = ran.index('parallel', n)
    assert ran[-100:].count('parallel') >= 90
    assert switched - n < 2 * parallel.PROBE_RATIO * 0.050 / 0.005
    costs['parallel'] = 0.050           # busy again
    n = len(ran)
    for _ in range(200):
        kernel(1)
    assert ran[n:].count('parallel') <= parallel.WINDOW
    assert ran[-20:].count('serial') >= 19


def test_work_normalises_calls_of_different_sizes():
    kernel, ran, _ = fake({'parallel': 0.004, 'serial': 0.010})   # per unit: parallel faster
    for size in (1, 1, 100, 100) + (10,) * 50:     # serial timed on a small call only
        kernel(size, work=size)
    assert ran[-20:].count('parallel') >= 19


@pytest.mark.parametrize('value, variant', [('serial', 'serial'), ('1', 'serial'),
                                            ('2', 'parallel'), (' 4 ', 'parallel')])
def test_the_environment_fixes_the_variant(monkeypatch, value, variant):
    monkeypatch.setenv(parallel.ENV, value)
    kernel, ran, _ = fake({'parallel': 1.0, 'serial': 0.001})
    for _ in range(50):
        kernel(1)
    assert set(ran) == {variant}


def test_set_mode_and_the_context_manager_override_the_environment(monkeypatch):
    monkeypatch.setenv(parallel.ENV, '2')
    kernel, ran, _ = fake({'parallel': 0.001, 'serial': 0.001})
    with parallel.mode('serial'):
        kernel(1)
        assert parallel.current_mode() == 'serial'
    kernel(1)
    assert ran == ['serial', 'parallel']


def test_one_core_runs_serial_only(monkeypatch):
    monkeypatch.setattr(parallel, 'machine_threads', lambda: 1)
    kernel, ran, _ = fake({'parallel': 0.001, 'serial': 0.1})
    for _ in range(100):
        kernel(1)
    assert set(ran) == {'serial'}


@pytest.mark.parametrize('value', ['fast', '0', '-2', '2.5'])
def test_an_unknown_mode_is_refused_saying_what_is_accepted(monkeypatch, value):
    monkeypatch.setenv(parallel.ENV, value)
    kernel, _, _ = fake({'parallel': 0.0, 'serial': 0.0})
    with pytest.raises(ValueError, match='auto, serial or a number of threads'):
        kernel(1)


def test_machine_threads_is_the_affinity_capped_by_numbas_pool():
    import os

    import numba
    assert 1 <= MACHINE_THREADS() <= min(len(os.sched_getaffinity(0)),
                                         numba.config.NUMBA_NUM_THREADS)


# -- the real kernels: both variants compute the same (bit for bit) --------------------------
@pytest.fixture
def real_threads(monkeypatch):
    monkeypatch.setattr(parallel, 'machine_threads', MACHINE_THREADS)


def _variants(run):
    """run() under the serial and under the parallel variant, with the calls each made."""
    results = {}
    for mode in ('serial', '2'):
        before = {k.name: dict(k.calls) for k in parallel.KERNELS}
        with parallel.mode(mode):
            out = run()
        # (a kernel module imported by run() is in KERNELS only from then on)
        ran = {k.name: {v: k.calls[v] - before.get(k.name, {}).get(v, 0) for v in k.calls}
               for k in parallel.KERNELS}
        results[mode] = (out, ran)
    return results


# The sweep's branches: the paper's model; a task stream; a queue (its own continuation kernel);
# the arm's keys (the robot's measured progress, the pauses under dp and dm, and its queue).
# The suite's other processes run the serial builds only (conftest.py), so these are the runs
# of the parallel builds that hold them to the serial ones
SWEEP_MODELS = {
    'paper': ('default', {}),
    'stream': ('default', {'stream': {'arrival_idle': 0.3, 'arrival_complete': 0.25,
                                      'q': [[1, 1, 0, 0.5], [1, 1, 3, 0.5]]}}),
    'queue': ('default', {'stream': {'arrival_idle': 0.3, 'arrival_busy': 0.25,
                                     'waiting_cost': 2.0, 'queue': 2,
                                     'q': [[1, 1, 0, 0.5], [1, 1, 3, 0.5]]}}),
    'arm': ('arm', {}),
}


@pytest.mark.parametrize('name', SWEEP_MODELS)
def test_the_mdp_sweep_is_the_same_serial_and_parallel(real_threads, name):
    from hrc_ros.core.config import load_config
    from hrc_ros.core.mdp.solver import solve
    from hrc_ros.core.model import HRCModel
    from hrc_ros.core.paths import shipped_config_path
    config, overrides = SWEEP_MODELS[name]
    model = HRCModel(load_config(shipped_config_path(config),
                                 overrides={'model': {'rho': 1, 'sigma': 1}, **overrides}))
    results = _variants(lambda: solve(model, sweeps=40))
    (serial, ran_serial), (par, ran_par) = results['serial'], results['2']
    kernels = ['hrc_ros.core.mdp._kernels.sweep']
    if model.n_levels > 1:
        kernels.append('hrc_ros.core.mdp._kernels.queue_continuations')
    assert (model.n_levels > 1) == (name in ('queue', 'arm'))
    for kernel in kernels:
        assert ran_serial[kernel]['serial'] > 0 and ran_serial[kernel]['parallel'] == 0, kernel
        assert ran_par[kernel]['parallel'] > 0 and ran_par[kernel]['serial'] == 0, kernel
    # 40 sweeps and the residual's, each a call per queue level
    assert ran_serial[kernels[0]]['serial'] == 41 * model.n_levels
    np.testing.assert_array_equal(serial.value, par.value)
    np.testing.assert_array_equal(serial.policy, par.policy)


def test_the_pomdp_backups_are_the_same_serial_and_parallel(real_threads):
    from hrc_ros.core.config import load_config
    from hrc_ros.core.model import HRCModel
    from hrc_ros.core.paths import default_config_path
    from hrc_ros.core.pomdp import solver as pomdp_solver
    model = HRCModel(load_config(default_config_path(), overrides={'model': {'rho': 1,
                                                                             'sigma': 1}}))
    hrc = pomdp_solver.hrc_pomdp(model)
    points_x, points = pomdp_solver._fixed_points(hrc)

    import copy
    start = pomdp_solver.initial_bounds(hrc.pomdp, points_x, points)

    def run():
        alphas, upper = copy.deepcopy(start)        # backup_sweeps updates the bound in place
        alphas, upper, history = pomdp_solver.backup_sweeps(
            hrc.pomdp, points_x, points, alphas, upper, max_sweeps=6, tol=0.0, ub_every=3)
        return alphas, upper, upper.evaluate(points_x, points)

    results = _variants(run)
    (a_s, u_s, e_s), ran_serial = results['serial']
    (a_p, u_p, e_p), ran_par = results['2']
    for kernel in ('lb_backup', 'ub_backup', 'lb_values', 'ub_values'):
        name = f'hrc_ros.core.pomdp._kernels.{kernel}'
        assert ran_serial[name]['serial'] > 0 and ran_serial[name]['parallel'] == 0
        assert ran_par[name]['parallel'] > 0 and ran_par[name]['serial'] == 0
    np.testing.assert_array_equal(a_s.alpha, a_p.alpha)
    np.testing.assert_array_equal(a_s.action, a_p.action)
    np.testing.assert_array_equal(u_s.values, u_p.values)
    np.testing.assert_array_equal(u_s.corner, u_p.corner)
    np.testing.assert_array_equal(e_s, e_p)
    # the sparse successors' sums (a queue's bounds: mdp_q, fib and the blind vectors, fast)
    results = _variants(lambda: pomdp_solver.mdp_q(hrc.pomdp, tol=1e-6, fast=True))
    (q_s, ran_serial), (q_p, ran_par) = results['serial'], results['2']
    name = 'hrc_ros.core.pomdp._kernels.successor_sums'
    assert ran_serial[name]['serial'] > 0 and ran_serial[name]['parallel'] == 0
    assert ran_par[name]['parallel'] > 0 and ran_par[name]['serial'] == 0
    np.testing.assert_array_equal(q_s, q_p)


def test_the_fit_e_step_is_the_same_serial_and_parallel(real_threads):
    from test_fit import random_data, random_params

    from hrc_ros.core.learning import fit
    rng = np.random.default_rng(11)
    data = random_data(rng, [30, 25, 40, 12, 33])
    x = np.stack([fit._pack(random_params(rng)) for _ in range(5)])
    weights = rng.integers(0, 3, size=(5, data.segments)).astype(float)
    name = 'hrc_ros.core.learning._kernels.e_step_batch'

    def run():
        single = fit.e_step(fit._unpack(x[0], random_params(rng)), data)   # split in halves
        return fit.e_step_batch(x, data, weights), single
    results = _variants(run)
    ((batch_s, impossible_s), single_s), ran_serial = results['serial']
    ((batch_p, impossible_p), single_p), ran_par = results['2']
    assert ran_serial[name] == {'serial': 2, 'parallel': 0}
    assert ran_par[name] == {'serial': 0, 'parallel': 2}
    np.testing.assert_array_equal(impossible_s, impossible_p)
    for f in ('loglik', 'first', 'accept', 'delta', 'transitions', 'observed', 'unique_moves'):
        np.testing.assert_array_equal(getattr(batch_s, f), getattr(batch_p, f), err_msg=f)
        np.testing.assert_array_equal(getattr(single_s, f), getattr(single_p, f), err_msg=f)
    # each lane of the batch is that lane's E-step alone
    for lane in range(5):
        alone = fit.e_step(fit._unpack(x[lane], random_params(rng)), data, weights[lane])
        assert alone.loglik == pytest.approx(float(batch_s.loglik[lane]), rel=1e-12)
        np.testing.assert_allclose(alone.transitions, batch_s.transitions[lane], rtol=1e-12)


def test_descendants_names_a_grandchild_and_not_the_parent():
    import os
    import subprocess
    import sys
    code = ('import subprocess, sys; p = subprocess.Popen([sys.executable, "-c", '
            '"import sys; sys.stdin.read()"], stdin=subprocess.PIPE); print(p.pid, flush=True); '
            'sys.stdin.read(); p.communicate("")')
    child = subprocess.Popen([sys.executable, '-c', code], stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, text=True)
    try:
        grandchild = int(child.stdout.readline())
        found = parallel.descendants(os.getpid())
        assert {child.pid, grandchild} <= found
        assert os.getpid() not in found and os.getppid() not in found
    finally:
        child.communicate('', timeout=60)


def test_the_warm_up_runs_only_where_a_kernel_file_has_no_current_cache(tmp_path,
                                                                         monkeypatch):
    """`hrc_ros.tools.warm --if-needed` (scripts/test.sh, before the whole suite): due unless
    the stamp of the last complete warm-up matches today's kernel sources, numba, Python and
    mode, and each kernel file's __pycache__ holds a numba index of its own at least as new as
    the source (an index of another file, or an older one, does not count; where
    NUMBA_CACHE_DIR puts the cache elsewhere only the stamp counts)."""
    import os
    from hrc_ros.tools.warm import KERNEL_FILES, STAMP, main, needed, stamp_path, stamp_text
    monkeypatch.delenv('NUMBA_CACHE_DIR', raising=False)
    kernels = [n for n in KERNEL_FILES if n.endswith('_kernels.py')]
    for name in KERNEL_FILES:
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(f'# {name}\n')
    assert needed(tmp_path) == [STAMP, *kernels]
    stamp = stamp_path(tmp_path)
    assert stamp == tmp_path / 'core' / '__pycache__' / STAMP
    stamp.parent.mkdir()
    stamp.write_text(stamp_text(tmp_path))
    assert needed(tmp_path) == kernels
    mdp = tmp_path / 'core/mdp/_kernels.py'
    cache = mdp.parent / '__pycache__'
    cache.mkdir()
    (cache / 'other._sweep-91.py311.nbi').write_bytes(b'')     # another file's index
    assert 'core/mdp/_kernels.py' in needed(tmp_path)
    index = cache / '_kernels._sweep-91.py311.nbi'
    index.write_bytes(b'')
    assert needed(tmp_path) == [n for n in kernels if n != 'core/mdp/_kernels.py']
    source_time = mdp.stat().st_mtime
    os.utime(index, (source_time - 10, source_time - 10))         # the source changed since
    assert 'core/mdp/_kernels.py' in needed(tmp_path)
    monkeypatch.setenv('NUMBA_CACHE_DIR', str(tmp_path / 'elsewhere'))
    assert needed(tmp_path) == []
    (tmp_path / 'core/parallel.py').write_text('# changed\n')      # the stamp is of other code
    assert needed(tmp_path) == [STAMP]
    with pytest.raises(SystemExit) as refused:
        main(['--jobs', '0'])
    assert refused.value.code == 2


def test_the_suites_processes_run_numpys_blas_on_one_thread():
    """conftest.py and scripts/test.sh: OpenBLAS's spinning threads took the core the other
    worker needed (test_fit_prior's recovery test 58.5 s beside two busy loops, 11.3 s with
    one thread). This process and a node or command it starts both run one BLAS thread."""
    import subprocess
    import sys
    # OpenBLAS's thread count, asked of the library numpy's wheel bundles (as `threads`)
    query = ('import ctypes, glob, os, numpy\n'
             'lib, = glob.glob(os.path.join(os.path.dirname(numpy.__file__), "..", '
             '"numpy.libs", "libscipy_openblas*"))\n'
             'threads = ctypes.CDLL(lib).scipy_openblas_get_num_threads64_()\n')
    here: dict = {}
    exec(query, here)
    assert here['threads'] == 1
    child = subprocess.run([sys.executable, '-c', query + 'print(threads)\n'],
                           capture_output=True, text=True, timeout=60)
    assert child.returncode == 0 and child.stdout.strip() == '1', child.stderr
