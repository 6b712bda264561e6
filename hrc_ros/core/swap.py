"""The live swap: which new configuration (and policy) a running node takes, one rule for both.

The decision node and the belief estimator take a new `config` while they run (and the
decision node a new `policy`; docs/LEARNING.md). The running cell's state space is fixed by
rho (priorities) and sigma (durations): every node holds task states, queues and a policy of
that size, and the task manager and the simulated cell read their configuration once. So the
rule, for both nodes alike (`check_swap`):

- the values in use: nothing to do (`SAME`);
- a configuration that does not load, or describes another cell size (other rho or sigma):
  `REFUSED`, with the reason (restart the nodes to change the state space);
- for the decision node, a configuration whose `model.robot_paused_by` differs from the
  running one's: `REFUSED` (the task manager keeps the robot's counter by the rule it started
  with, so the planner would plan with another task step than the cell's; restart the nodes);
  the same for one that has `model.robot_rate` (the arm's measured progress) where the running
  one has none, or the other way round (the cell runs with or without the arm by how it
  started: the task manager refuses a rated model without the arm's progress at start);
- for the decision node, a policy that does not exist, is not a policy, or was not solved for
  the configuration set with it: `REFUSED`; a configuration set alone while the policy in use
  was not solved for it: `STAGED` (the old pair keeps deciding until a policy for it is set,
  so one-at-a-time `ros2 param set` can change both);
- for the decision node, the POMDP policy (`pomdp_policy`: '' is the shipped one solved for
  the configuration, `policies/pomdp/`) when its selector reads one (pomdp, fib) or when
  the value was just set: checked as the policy is, by the configuration's and the
  observation model's hashes: set in this change and wrong, `REFUSED`; unchanged and no
  longer matching the configuration set, `STAGED` (set `pomdp_policy` next);
- otherwise `ACCEPTED`: the node loads the new pair off its executor and swaps it in at the
  next epoch boundary.

The policy a `policy` value names is `policy_path` (the default-policy rule: '' is the shipped
policy solved for the configuration, else `policies/default.npz`), here only. Only file metas
are read (milliseconds): the full check of the arrays is the background load's.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from .config import Config, ConfigError, load_config
from .mdp.policy import PolicyError, default_policy_path, peek_policy
from .paths import default_config_path
from .quoting import cap    # a reason goes back through the parameter service: capped

SAME, REFUSED, STAGED, ACCEPTED = 'same', 'refused', 'staged', 'accepted'


def config_path(value: str) -> str:
    """The file a `config` parameter names ('' = the shipped default.yaml)."""
    return value if value else str(default_config_path())


def policy_path(value: str, config: Config) -> str:
    """The file a `policy` parameter names for `config` (the default-policy rule)."""
    return value if value else str(default_policy_path(config))


def load_node_config(value: str) -> Config:
    """The configuration a `config` parameter names; ConfigError says why it does not load."""
    return load_config(config_path(value))


@dataclass(frozen=True)
class SwapCheck:
    """The verdict on a proposed (config, policy): one of SAME, REFUSED, STAGED, ACCEPTED, the
    reason (REFUSED, STAGED) and the configuration it loaded."""

    verdict: str
    reason: str = ''
    config: Config | None = None

    @property
    def refused(self) -> bool:
        return self.verdict == REFUSED


def check_swap(rho: int, sigma: int, running_config: str, config_value: str,
               running_policy: str | None = None, policy_value: str | None = None,
               load: Callable[[str], Config] = load_node_config,
               paused: tuple | None = None, queue: int | None | bool = False,
               running_pomdp: str | None = None, pomdp_value: str | None = None,
               pomdp_needed: bool = False, rated: bool | None = None) -> SwapCheck:
    """The swap rule (module docstring) for a running cell of size (rho, sigma) whose node runs
    the parameter values `running_config` (and `running_policy`: the decision node; None for a
    node without a policy) and is asked for `config_value` (and `policy_value`); `paused`: the
    running configuration's `robot_paused_by` (the decision node; None: not checked);
    `queue`: its `stream.queue` (None: no queue; False: not checked); `running_pomdp` and
    `pomdp_value`: the decision node's `pomdp_policy` in use and asked for (None: a node
    without one), `pomdp_needed`: its selector reads the POMDP policy; `rated`: whether the
    running configuration has `model.robot_rate` (None: not checked)."""
    with_policy = running_policy is not None
    pomdp_changed = running_pomdp is not None and pomdp_value != running_pomdp
    if config_value == running_config and not pomdp_changed \
            and (not with_policy or policy_value == running_policy):
        return SwapCheck(SAME)
    try:
        config = load(config_value)
    except Exception as exc:  # noqa: BLE001 - whatever a file does, the old pair keeps running
        reason = str(exc) if isinstance(exc, ConfigError) else f'{type(exc).__name__}: {exc}'
        return SwapCheck(REFUSED, cap(f'config refused: bad model configuration: {reason}'))
    if (config.rho, config.sigma) != (rho, sigma):
        return SwapCheck(REFUSED, f'config refused: {config.source} has rho {config.rho}, '
                         f'sigma {config.sigma}; the running cell {rho}, {sigma}: restart the '
                         'nodes to change the state space', config)
    if paused is not None and tuple(config.robot_paused_by) != tuple(paused):
        return SwapCheck(REFUSED, f'config refused: {config.source} pauses the robot\'s '
                         f'counter under {", ".join(config.robot_paused_by)}, the running '
                         f'configuration under {", ".join(paused)} (MODEL.md 3.2), and the task '
                         'manager keeps it by the rule it started with: restart the nodes',
                         config)
    if rated is not None and (config.robot_rate is not None) != rated:
        def counted(has_rate):
            return ("counts the robot's share by the arm's measured progress (model.robot_rate)"
                    if has_rate else "counts the robot's share down every epoch it works "
                    '(no model.robot_rate)')
        return SwapCheck(REFUSED, f'config refused: {config.source} {counted(not rated)}, the '
                         f'running configuration {counted(rated)} (MODEL.md 3.2), and the cell '
                         'runs with or without the arm by how it started: restart the nodes',
                         config)
    if queue is not False and config.queue != queue:
        def said(length):
            return 'no queue' if length is None else f'a queue of {length}'
        return SwapCheck(REFUSED, f'config refused: {config.source} has {said(config.queue)}, '
                         f'the running configuration {said(queue)} (stream.queue, MODEL.md '
                         '8.1), and the task manager publishes the tasks waiting by the rule '
                         'it started with: restart the nodes', config)
    if not with_policy:
        return SwapCheck(ACCEPTED, config=config)
    staged = None
    try:
        peek_policy(Path(policy_path(policy_value, config)), config)
    except Exception as exc:  # noqa: BLE001 - PolicyError, or whatever a damaged file raises
        if not isinstance(exc, PolicyError):
            exc = f'{type(exc).__name__}: {exc}'
        elif policy_value == running_policy:
            staged = SwapCheck(STAGED, cap(str(exc)), config)
        else:
            return SwapCheck(REFUSED, cap(f'policy refused: {exc} (the configuration set is '
                                           f'{config.source}; to change both, set config '
                                           'first, then policy)'), config)
    # the POMDP policy: one just set is checked against the configuration set (refused when
    # wrong, even while the set waits for its MDP policy), one left as it was only when the
    # selector reads it (staged when it no longer matches)
    if running_pomdp is not None and (pomdp_needed or (pomdp_changed and pomdp_value)):
        from .pomdp.policy import peek_pomdp_policy, pomdp_policy_path   # the POMDP's, lazily
        try:
            peek_pomdp_policy(pomdp_policy_path(pomdp_value, config), config)
        except Exception as exc:  # noqa: BLE001 - PolicyError, or whatever a damaged file raises
            if not isinstance(exc, PolicyError):
                exc = f'{type(exc).__name__}: {exc}'
            elif not pomdp_changed:
                return staged or SwapCheck(STAGED, cap(f'{exc} (set pomdp_policy to a POMDP '
                                                       'policy solved for it)'), config)
            return SwapCheck(REFUSED, cap(f'pomdp_policy refused: {exc} (the configuration set '
                                           f'is {config.source}; to change both, set config '
                                           'first, then pomdp_policy and policy)'), config)
    if staged is not None:
        return staged
    return SwapCheck(ACCEPTED, config=config)
