"""`hrc-fleet run --apply`: swap each promoted cell's policy on its running nodes.

The existing live swap (docs/LEARNING.md 4), through the parameter services of the cell's
nodes in its namespace: first the decision node's `selector` is read (a node running another
selector than the plant checked the cell with, or one without a selector parameter, is `not
applied`, nothing changed). The files set are copies of the cell's in
`cells/<cell>/live/<digest>/`, named by their content (`live_copy`): the node compares
parameter values, so the next night's files written over the same paths would be the set in
use to it. Then the belief estimator's `config` (when it runs), then the decision node's
`config`, for a cell whose selector is pomdp or fib its `pomdp_policy` (the POMDP policy the
plant solved) and its `policy` in one atomic set (as `ros2 param load` sets a file), so the
node checks the set whole and takes it whole, swapping it in at the next epoch boundary, or
refuses it whole. Then the swap is verified from what the node publishes, not from what was
set: a decision status of `<namespace>/decision` on /diagnostics whose `policy_file` is the
new policy, whose `config_sha256` is the fitted configuration's (the policy identity every
decision status carries) and, for pomdp and fib, whose `pomdp_policy_file` is the new POMDP
policy; or its status that it refused the set at the boundary (its full load found what the
quick check could not). Whenever the swap did not happen, the estimator's `config` is set
back.

Per cell the result is one of `swapped` (verified), `not running` (no decision node answers
in the namespace: reported, the other cells go on), `not applied` (not the cell's node),
`refused` (the node's reason, at the set or at the boundary) or `not verified` (set, but no
status named the new policy within the timeout; or applying stopped on an error, named).
The files must be readable by the nodes: the paths are absolute, on this machine.
"""

from __future__ import annotations

import hashlib
import shutil
import time
from pathlib import Path

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from rcl_interfaces.msg import ParameterType

from ..core.paths import replace_file
from ..core.plant.spec import POMDP_SELECTORS
from ..core.quoting import cap
from . import conversions as conv
from . import qos
from .node_support import DIAGNOSTICS_TOPIC

SERVICE_WAIT = 3.0      # seconds for a node's parameter services to show up
SET_TIMEOUT = 10.0


class Applier:
    """A node of its own (own Context) that sets parameters and watches /diagnostics."""

    def __init__(self):
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node('hrc_fleet_apply', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.statuses: list = []
        self.node.create_subscription(DiagnosticArray, DIAGNOSTICS_TOPIC, self._on_diagnostics,
                                      qos.RELIABLE)

    def _on_diagnostics(self, msg) -> None:
        for status in msg.status:
            self.statuses.append((status.name, conv.diagnostic_values(status)))

    def spin_until(self, predicate, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while not predicate():
            if time.monotonic() > deadline:
                return False
            self.executor.spin_once(timeout_sec=0.05)
        return True

    def client(self, name: str) -> AsyncParameterClient | None:
        client = AsyncParameterClient(self.node, name)
        if not client.wait_for_services(timeout_sec=SERVICE_WAIT):
            return None
        return client

    def set(self, client: AsyncParameterClient, name: str, value: str):
        future = client.set_parameters([Parameter(name, value=value)])
        if not self.spin_until(future.done, SET_TIMEOUT):
            return False, f'setting {name} timed out after {SET_TIMEOUT:g} s'
        result = future.result().results[0]
        return result.successful, result.reason

    def set_atomically(self, client: AsyncParameterClient, values: dict):
        """Every (name, value) in one set: checked together, taken together or not at all."""
        future = client.set_parameters_atomically(
            [Parameter(name, value=value) for name, value in values.items()])
        if not self.spin_until(future.done, SET_TIMEOUT):
            return False, f'setting {", ".join(values)} timed out after {SET_TIMEOUT:g} s'
        result = future.result().result
        return result.successful, result.reason

    def get(self, client: AsyncParameterClient, names: list[str]) -> dict | None:
        """The string parameters `names` of a node that it has (None when it does not
        answer; a name it does not declare is left out: the service answers no value)."""
        future = client.get_parameters(names)
        if not self.spin_until(future.done, SET_TIMEOUT):
            return None
        values = future.result().values
        if len(values) != len(names):     # one undeclared: which is unknown, none is trusted
            return {}
        return {name: value.string_value for name, value in zip(names, values)
                if value.type == ParameterType.PARAMETER_STRING}

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)

    # -- one cell ------------------------------------------------------------------------
    def apply(self, namespace: str, folder: Path, config_sha256: str, timeout: float,
              selector: str = 'paper') -> dict:
        """One promoted cell whose files (fitted.yaml, policy.npz and for pomdp and fib
        pomdp.npz) are in `folder`; they are set as copies named by their content
        (`live_copy`) once the node is found to be the cell's."""
        prefix = namespace.rstrip('/')
        decision = self.client(f'{prefix}/decision')
        if decision is None:
            return {'status': 'not running', 'detail': f'no decision node answers at '
                    f'{prefix}/decision; nothing changed'}
        running = self.get(decision, ['selector'])
        if running is None:
            return {'status': 'not verified', 'detail': f'{prefix}/decision did not answer '
                    f'for its selector within {SET_TIMEOUT:g} s; nothing changed'}
        if 'selector' not in running:
            return {'status': 'not applied', 'detail': (
                f'{prefix}/decision has no selector parameter: not an hrc_ros decision node; '
                'nothing changed')}
        if running['selector'] != selector:
            return {'status': 'not applied', 'detail': (
                f'{prefix}/decision runs selector {running["selector"]}, the plant checked '
                f'the cell with {selector}: nothing changed (set the cell\'s selector in the '
                'plant file to the one it runs)')}
        live = live_copy(folder, ('fitted.yaml', 'policy.npz')
                         + (('pomdp.npz',) if selector in POMDP_SELECTORS else ()))
        config, policy, pomdp = live['fitted.yaml'], live['policy.npz'], live.get('pomdp.npz')
        notes = []
        estimator = self.client(f'{prefix}/belief_estimator')
        before = None if estimator is None else self.get(estimator, ['config'])
        if estimator is None or not before:
            notes.append(f'no belief estimator answers at {prefix}/belief_estimator, its '
                         'configuration was not set')
            estimator = None
        else:
            ok, reason = self.set(estimator, 'config', config)
            if not ok:
                return {'status': 'refused', 'detail': f'belief_estimator config: {reason}'}
        # the decision node's set in one atomic set: checked whole, taken whole or not at all
        # (one at a time, a refusal would leave the configuration staged)
        wanted = {'config': config, **({} if pomdp is None else {'pomdp_policy': pomdp}),
                  'policy': policy}
        who = f'{prefix.lstrip("/")}/decision: ' if prefix else 'decision: '
        since = len(self.statuses)

        def undone(result: dict) -> dict:
            """The swap did not happen: the estimator back to what it ran, as the decision
            node is (it sets its own parameters back on a refusal)."""
            if estimator is not None:
                ok, reason = self.set(estimator, 'config', before['config'])
                result['detail'] += ('; the belief estimator\'s configuration was set back' if ok
                                     else f'; setting the belief estimator\'s configuration '
                                     f'back failed: {reason}')
            return result
        ok, reason = self.set_atomically(decision, wanted)
        if not ok:
            return undone({'status': 'refused',
                           'detail': f'decision {", ".join(wanted)}: {reason}'})

        def reported() -> bool:
            return any(name.startswith(who) and values.get('policy_file') == policy
                       and values.get('config_sha256') == config_sha256
                       and (pomdp is None or values.get('pomdp_policy_file') == pomdp)
                       for name, values in self.statuses)

        def refusal() -> str | None:
            """The node's error when it took the set and refused it at the boundary (its
            full load found what the quick check could not)."""
            return next((values['error'] for name, values in self.statuses[since:]
                         if name == who + 'policy' and 'error' in values), None)
        if not self.spin_until(lambda: reported() or refusal() is not None, timeout):
            return undone({'status': 'not verified', 'detail': f'{policy} was accepted, but no '
                           f'status of {prefix}/decision named it within {timeout:g} s'})
        if not reported():
            return undone({'status': 'refused', 'detail': f'{prefix}/decision took the set and '
                           f'refused it at the epoch boundary: {refusal()}'})
        epoch = next(values.get('epoch') for name, values in self.statuses
                     if name.startswith(who) and values.get('policy_file') == policy)
        both = '' if pomdp is None else f' and POMDP policy {pomdp}'
        return {'status': 'swapped', 'detail': '; '.join(
            [f'{prefix}/decision reports policy {policy}{both} (config sha256 '
             f'{config_sha256[:12]}) from epoch {epoch}'] + notes)}


def apply_promoted(entries: list[dict], timeout: float = 30.0) -> dict:
    """cell -> result (module docstring) for every promoted entry of a plant report."""
    promoted = [e for e in entries if e['decision'] == 'promote']
    if not promoted:
        return {}
    applier = Applier()
    try:
        out = {}
        for entry in promoted:
            try:
                out[entry['cell']] = applier.apply(
                    entry['namespace'], Path(entry['folder']).resolve(),
                    entry['fit']['config_sha256'], timeout, entry.get('selector') or 'paper')
            except Exception as exc:  # noqa: BLE001 - one cell's surprise is its own result
                out[entry['cell']] = {'status': 'not verified', 'detail': (
                    f'applying stopped: {type(exc).__name__}: {cap(str(exc))}')}
        return out
    finally:
        applier.close()


def live_copy(folder: Path, names: tuple) -> dict[str, str]:
    """name -> path of a copy of each file in `folder/live/<digest of them all>/`. The swap
    rule compares parameter values, so a node that runs last night's `cells/<cell>/policy.npz`
    would take tonight's, written over it at the same path, as the set in use and keep the
    old one it holds; each set of files gets its own paths, and the same files again the same
    paths (nothing to swap). Each copy is written whole or not at all."""
    digest = hashlib.sha256()
    for name in names:
        digest.update(name.encode() + b'\0' + (folder / name).read_bytes())
    target = folder / 'live' / digest.hexdigest()[:16]
    target.mkdir(parents=True, exist_ok=True)
    for name in names:
        if not (target / name).is_file():
            replace_file(target / name, lambda temporary, source=folder / name:
                         shutil.copyfile(source, temporary))
    return {name: str(target / name) for name in names}
