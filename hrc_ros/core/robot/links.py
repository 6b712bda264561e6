"""The distance level d from the arm's links: the belief estimator's `distance_source:
arm_links` (docs/ROBOT.md, "the graph with the arm"), as a sans-IO machine.

The batch cell (`robot.cell`) gives the decision layer d_k = `level_of_distance` of the
separation between the arm's link capsules and the person's body capsules (`Arm.separation`,
`body_capsules`), against `safety_radii`; this is the same rule for a graph, fed the arm's
joint states and the skeletons as they arrive:

    joint_state(names, positions, stamp, now)  the arm's sensor_msgs/JointState
    level(keypoints, stamp_ns) -> LinkLevel    each skeleton's d (at its stamp), and why

**Stale arm state** (decision). The arm's joint state is fresh for a skeleton while it is at
most the robot description's `joint_state_timeout` (the bridge's own bound: 0.1 s for the
UR5e) older than the skeleton, both by their stamps: the arm as it stood when the person was
seen, whatever the reader's own delay (a loaded estimator that takes both late still pairs
them right; an arm whose stream stopped ages out while the skeletons keep coming). Without
a fresh one the estimator cannot place the links: they may stand anywhere within the arm's
reach, and at the shared table the person stands within it. The reference point's band would
then overstate the separation (a person 1.4 m from the base is "outer" while a link can be 0.3
m from them), so the level is 0, the collision level, with the reason: the decision node fails
safe (dn, the arm held) until the arm's state is back, as the bridge itself stops the arm
without it. The node reports the reason as a WARN diagnostic.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..decision.observation import level_of_distance
from ..protocol import InputError
from .arm import Arm, Separation, body_capsules
from .bridge import JointStateReader, RobotDescription, check_stamp


@dataclass(frozen=True)
class LinkLevel:
    """A skeleton's distance level d, the separation it is the band of (None: no fresh arm
    state, then d = 0), and why there is none ('' when there is)."""

    d: int
    separation: Separation | None
    reason: str = ''


class LinkDistance:
    """d from the separation of the arm's links to each skeleton (see the module docstring).

    `joints`: the skeleton's K4ABT joint names per body (bones between them), None: a sphere
    around each keypoint (`arm.body_capsules`)."""

    def __init__(self, description: RobotDescription, radii, joints=None, arm: Arm | None = None):
        self.reader = JointStateReader(description)
        self.timeout_ns = int(round(description.joint_state_timeout * 1e9))
        self.radii = tuple(float(r) for r in radii)
        self.joints = tuple(joints) if joints else None
        self.arm = arm if arm is not None else Arm()
        self.q: np.ndarray | None = None
        self.stamp_ns: int | None = None
        # The kernels' first call loads them (seconds on a loaded machine): here, before a
        # node subscribes anything, not at the first skeleton of a running cell.
        self.arm.separation(description.poses['home'], body_capsules(np.ones((1, 3))))

    def joint_state(self, names, positions, stamp_ns: int, now_ns: int) -> None:
        """The arm's joint state at `now_ns` of the reader's clock (InputError, nothing kept,
        as the bridge refuses it: also one stamped ahead of the clock, which would pair with
        skeletons after the arm's stream stopped)."""
        check_stamp('arm joint state', stamp_ns, now_ns)
        q, _ = self.reader.read(names, positions)
        if self.stamp_ns is not None and stamp_ns < self.stamp_ns:
            raise InputError('arm joint state older than the one held: dropped')
        self.q, self.stamp_ns = q, int(stamp_ns)

    def stale(self, stamp_ns: int) -> str:
        """Why the arm's state cannot be used for a skeleton stamped `stamp_ns` ('' when it
        can)."""
        if self.q is None:
            return 'no joint state of the arm yet'
        age = (stamp_ns - self.stamp_ns) * 1e-9
        if age > self.timeout_ns * 1e-9:
            return (f"the arm's joint state is {age:.3f} s older than the skeleton "
                    f'(joint_state_timeout {self.timeout_ns * 1e-9:g} s)')
        return ''

    def level(self, keypoints, stamp_ns: int) -> LinkLevel:
        """The distance level of one skeleton (n, 3), robot base frame, stamped `stamp_ns`;
        InputError for keypoints that make no body."""
        try:
            body = body_capsules(keypoints, self.joints)
        except ValueError as exc:
            raise InputError(f'skeleton: {exc}') from None
        reason = self.stale(stamp_ns)
        if reason:
            return LinkLevel(0, None, reason)
        separation = self.arm.separation(self.q, body)
        return LinkLevel(level_of_distance(separation.distance, self.radii), separation)
