"""What the ROS-free command lines share: the model and policy arguments and their loading."""

from __future__ import annotations

import argparse

from ..core.config import Config, ConfigError, load_config
from ..core.model import HRCModel
from ..core.paths import default_config_path
from ..core.policy import Policy, PolicyError, default_policy_path, load_policy


class ToolError(RuntimeError):
    """A command cannot run with what it was given; the text says why (exit status 2)."""


def add_model_arguments(parser: argparse.ArgumentParser, policy: bool = True) -> None:
    parser.add_argument('--config', default=None,
                        help='configuration YAML (default: the shipped default.yaml)')
    if policy:
        parser.add_argument('--policy', default=None,
                            help='policy file solved for that configuration (default: the '
                                 'shipped policy solved for it, e.g. paper.npz for paper.yaml)')


def load_model(args: argparse.Namespace) -> tuple[Config, HRCModel, Policy | None]:
    """The configuration, its model and (with a --policy argument) the policy for it."""
    try:
        config = load_config(args.config or default_config_path())
        policy = None
        if hasattr(args, 'policy'):
            policy = load_policy(args.policy or default_policy_path(config), config)
    except (ConfigError, PolicyError) as exc:
        raise ToolError(str(exc)) from None
    return config, HRCModel(config), policy


def add_pomdp_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--pomdp-policy', default=None,
                        help='POMDP policy file for the pomdp and fib selectors (default: the '
                             'shipped one solved for the configuration, policies/pomdp/)')


def load_pomdp(args: argparse.Namespace, config: Config, selectors) -> object | None:
    """The POMDP policy when one of `selectors` needs it (pomdp, fib), else None."""
    from ..core.pomdp_policy import default_pomdp_policy_path, load_pomdp_policy
    from ..core.selection import POMDP_SELECTORS
    if not any(s in POMDP_SELECTORS for s in selectors):
        return None
    try:
        return load_pomdp_policy(args.pomdp_policy or default_pomdp_policy_path(config), config)
    except PolicyError as exc:
        raise ToolError(str(exc)) from None
