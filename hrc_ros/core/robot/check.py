"""SSM checked from outside a run of the graph: the arm's joint states against the person's true
body at that instant (docs/ROBOT.md 4 and 6, "an honest check").

`cobot_sim_node`'s `hrc/separation` is the project's own check: S from the skeleton it holds,
which the tracker delivered some milliseconds ago (or never updated, if it froze), and S_p at
its speed bound with that skeleton's age. The simulator knows more: `cell_sim_node` (person 3d)
publishes every body in the cell on `hrc/sim/true_skeleton`, stamped when it was there. So each
joint state of a recorded run is checked against the true bodies at its own stamp (the two true
samples around it, interpolated: the people move at most 2 m/s, the samples come at 50 Hz),
with ISO/TS 15066's S_p as written at the arm's speed: the larger of its links' speed from the
joint state's velocities and the speed bound cobot_sim published with it. A sample breaks SSM
when the arm moves (> `ssm.MOVING_SPEED`) and S < S_p.

A joint state with no true sample within TRUTH_GAP (cell_sim stalled by a loaded machine: once
at load 9) is checked against the nearest true sample within TRUTH_REACH, the person taken
nearer by BODY_SPEED times the time between them (they may have come that far), and counted as
`bridged`: the check stays on the safe side instead of leaving the sample out. Only a joint
state with no true sample within TRUTH_REACH is `unchecked`.
"""

from __future__ import annotations

import math
from bisect import bisect_left

import numpy as np

from ..cell.tracking import K4ABT_JOINTS
from .arm import Arm, body_capsules
from .ssm import MOVING_SPEED, protective_distance

TRUTH_GAP = 0.1      # s: within this of true samples, the truth is interpolated between them
TRUTH_REACH = 1.0    # s: farther from any true sample, a joint state is not checked (counted)
BODY_SPEED = 2.0     # m/s: the fastest the simulated people move (a reach, ISO 13855's 2.0)
PAIR_SLACK = 2e-3    # s between a joint state and the hrc/separation published with it


def ssm_check(joints, truth, separations, description, arm: Arm | None = None,
              keypoint_joints=K4ABT_JOINTS) -> dict:
    """The check of the module docstring.

    joints: (stamp ns, published ns, q (6,), qd (6,)) per joint state, in time order;
    truth: (stamp ns, keypoints (n, 3)) per true sample, in time order;
    separations: (published ns, [S, arm xyz, human xyz, S_p, speed]) per hrc/separation.
    Returns the counts, the violations and the smallest margins, by the truth and by the
    project's own hrc/separation."""
    arm = arm or Arm()
    p = description.ssm
    names = tuple(keypoint_joints)
    truth_t = [t for t, _ in truth]
    pub_t = [t for t, _ in separations]
    out = {'joint_states': 0, 'moving': 0, 'unchecked': 0, 'bridged': 0, 'violations': 0,
           'min_margin_m': math.inf, 'min_separation_moving_m': math.inf,
           'own_samples': len(separations), 'own_moving': 0, 'own_violations': 0,
           'own_min_margin_m': math.inf, 'worst': None}
    for stamp, published, q, qd in joints:
        out['joint_states'] += 1
        speed = arm.link_speed(q, qd)
        j = bisect_left(pub_t, published)
        for k in (j - 1, j):
            if 0 <= k < len(pub_t) and abs(pub_t[k] - published) * 1e-9 <= PAIR_SLACK:
                speed = max(speed, float(separations[k][1][8]))
        if speed <= MOVING_SPEED:
            continue
        out['moving'] += 1
        bodies, gap = _true_bodies(truth, truth_t, stamp)
        if not bodies:
            out['unchecked'] += 1
            continue
        out['bridged'] += gap > 0.0
        distance = min(arm.distance(q, body_capsules(kp, names)) for kp in bodies) \
            - BODY_SPEED * gap
        margin = distance - float(protective_distance(speed, distance, p))
        out['min_separation_moving_m'] = min(out['min_separation_moving_m'], distance)
        if margin < out['min_margin_m']:
            out['min_margin_m'] = margin
            out['worst'] = {'stamp_ns': int(stamp), 'separation_m': distance,
                            'speed_m_s': speed, 'margin_m': margin}
        out['violations'] += margin < 0.0
    for _, values in separations:
        s, s_p, speed = float(values[0]), float(values[7]), float(values[8])
        if speed > MOVING_SPEED:
            out['own_moving'] += 1
            out['own_min_margin_m'] = min(out['own_min_margin_m'], s - s_p)
            out['own_violations'] += s < s_p
    for key in ('min_margin_m', 'min_separation_moving_m', 'own_min_margin_m'):
        if not math.isfinite(out[key]):
            out[key] = None
    return out


def _true_bodies(truth, times, stamp) -> tuple[list, float]:
    """The true keypoints at `stamp`, and how far in time (s) they may be from it: interpolated
    between the samples around it when both lie within TRUTH_GAP and hold the same bodies, else
    those within TRUTH_GAP (the nearer counts), gap 0; else the nearest sample within
    TRUTH_REACH and its time from `stamp` (module docstring); ([], 0) when none is."""
    i = bisect_left(times, stamp)
    before = truth[i - 1] if i > 0 else None
    after = truth[i] if i < len(truth) else None
    near = [s for s in (before, after) if s is not None
            and abs(s[0] - stamp) * 1e-9 <= TRUTH_GAP]
    if len(near) == 2 and before[1].shape == after[1].shape and after[0] > before[0]:
        u = (stamp - before[0]) / (after[0] - before[0])
        return [before[1] + (after[1] - before[1]) * u], 0.0
    if near:
        return [s[1] for s in near], 0.0
    reach = [(abs(s[0] - stamp) * 1e-9, s[1]) for s in (before, after) if s is not None]
    reach = [r for r in reach if r[0] <= TRUTH_REACH]
    if not reach:
        return [], 0.0
    gap, keypoints = min(reach, key=lambda r: r[0])
    return [keypoints], gap


def ssm_check_of_bag(path, description, namespace: str = '') -> dict:
    """`ssm_check` of a recorded run (a bag folder or .mcap file) of the graph with the arm and
    cell_sim's 3D person: /joint_states, /hrc/separation and /hrc/sim/true_skeleton."""
    from ..bagfile import read_bag
    prefix = namespace.rstrip('/')
    topics = {f'{prefix}/joint_states': 'joints', f'{prefix}/hrc/separation': 'separation',
              f'{prefix}/hrc/sim/true_skeleton': 'truth'}
    joints, truth, separations = [], [], []
    for message in read_bag(path, topics=list(topics), decode=True):
        kind, m = topics[message.topic], message.decoded
        if m is None:
            continue
        if kind == 'joints':
            names = list(m.name)
            if not all(n in names for n in description.joint_names):
                continue
            order = [names.index(n) for n in description.joint_names]
            q = np.asarray(m.position, dtype=float)[order]
            qd = np.asarray(m.velocity, dtype=float)[order] if len(m.velocity) else \
                np.zeros(len(order))
            joints.append((m.header.stamp.sec * 10**9 + m.header.stamp.nanosec,
                           message.publish_time_ns, q, qd))
        elif kind == 'separation':
            separations.append((message.publish_time_ns, list(m.data)))
        else:
            points = np.array([[p.position.x, p.position.y, p.position.z] for p in m.poses])
            if len(points):
                truth.append((m.header.stamp.sec * 10**9 + m.header.stamp.nanosec, points))
    joints.sort(key=lambda j: j[0])
    truth.sort(key=lambda t: t[0])
    separations.sort(key=lambda s: s[0])
    return ssm_check(joints, truth, separations, description)


def format_ssm_check(result: dict) -> str:
    def metres(value):
        return '-' if value is None else f'{value:+.3f} m'
    return (f'SSM against the true bodies (hrc/sim/true_skeleton): {result["joint_states"]} '
            f'joint states, {result["moving"]} with the arm moving, {result["violations"]} with '
            f'S < S_p, smallest margin {metres(result["min_margin_m"])}'
            + (f', {result["bridged"]} checked across a gap in the truth (the person taken '
               f'nearer by {BODY_SPEED:g} m/s over it)' if result.get('bridged') else '')
            + (f', {result["unchecked"]} without a true sample within {TRUTH_REACH:g} s'
               if result['unchecked'] else '')
            + f'; by cobot_sim\'s own hrc/separation: {result["own_violations"]} of '
            f'{result["own_moving"]} moving samples, smallest margin '
            f'{metres(result["own_min_margin_m"])}')


__all__ = ['format_ssm_check', 'ssm_check', 'ssm_check_of_bag']
