"""`hrc-fleet run --apply`: swap each promoted cell's policy on its running nodes.

The existing live swap (docs/LEARNING.md 4), done as `ros2 param set` does it, through the
parameter services of the cell's nodes in its namespace: the belief estimator's `config` (when
it runs), then the decision node's `config`, for a cell whose selector is pomdp or fib its
`pomdp_policy` (the POMDP policy the plant solved), then its `policy` (the node checks the set
at once and swaps it in at the next epoch boundary). Then the swap is verified from what the
node publishes, not from what was set: a decision status of `<namespace>/decision` on
/diagnostics whose `policy_file` is the new policy, whose `config_sha256` is the fitted
configuration's (the policy identity every decision status carries) and, for pomdp and fib,
whose `pomdp_policy_file` is the new POMDP policy.

Per cell the result is one of `swapped` (verified), `not running` (no decision node answers
in the namespace: reported, the other cells go on), `refused` (a parameter was refused: the
node's reason) or `not verified` (set, but no status named the new policy within the timeout).
The files must be readable by the nodes: the paths are absolute, on this machine.
"""

from __future__ import annotations

import time
from pathlib import Path

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient

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

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)

    # -- one cell ------------------------------------------------------------------------
    def apply(self, namespace: str, config: str, policy: str, config_sha256: str,
              timeout: float, pomdp: str | None = None) -> dict:
        prefix = namespace.rstrip('/')
        decision = self.client(f'{prefix}/decision')
        if decision is None:
            return {'status': 'not running', 'detail': f'no decision node answers at '
                    f'{prefix}/decision; nothing changed'}
        notes = []
        estimator = self.client(f'{prefix}/belief_estimator')
        if estimator is None:
            notes.append(f'no belief estimator at {prefix}/belief_estimator, its configuration '
                         'was not set')
        else:
            ok, reason = self.set(estimator, 'config', config)
            if not ok:
                return {'status': 'refused', 'detail': f'belief_estimator config: {reason}'}
        for name, value in (('config', config), ('pomdp_policy', pomdp), ('policy', policy)):
            if value is None:
                continue
            ok, reason = self.set(decision, name, value)
            if not ok:
                return {'status': 'refused', 'detail': f'decision {name}: {reason}'}
        who = f'{prefix.lstrip("/")}/decision: ' if prefix else 'decision: '

        def reported() -> bool:
            return any(name.startswith(who) and values.get('policy_file') == policy
                       and values.get('config_sha256') == config_sha256
                       and (pomdp is None or values.get('pomdp_policy_file') == pomdp)
                       for name, values in self.statuses)
        if not self.spin_until(reported, timeout):
            return {'status': 'not verified', 'detail': f'{policy} was accepted, but no status '
                    f'of {prefix}/decision named it within {timeout:g} s'}
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
            folder = Path(entry['folder']).resolve()
            pomdp = (str(folder / 'pomdp.npz') if entry.get('selector') in ('pomdp', 'fib')
                     else None)
            out[entry['cell']] = applier.apply(
                entry['namespace'], str(folder / 'fitted.yaml'), str(folder / 'policy.npz'),
                entry['fit']['config_sha256'], timeout, pomdp)
        return out
    finally:
        applier.close()
