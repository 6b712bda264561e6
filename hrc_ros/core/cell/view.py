"""The cell as a picture: the markers `cell_view_node` publishes on `hrc/markers` (ROS-free).

`scene(state, radii, reference_point)` describes the whole picture as `Shape`s in the robot
frame (metres); `hrc_ros.ros.conversions.markers_to_msg` turns them into a
`visualization_msgs/MarkerArray` that starts with a DELETEALL, so every message replaces the
previous picture and nothing accumulates in RViz or Foxglove. The shapes, by namespace:

- ``safety``: the three safety circles around the robot reference point p, flat translucent
  discs of radius r0 (collision), r1 (inner) and r2 (middle), each in the colour of the level
  inside it (`LEVEL_COLORS`);
- ``robot``: p itself;
- ``human``: the keypoints of the latest skeleton, coloured by *their* distance level (the
  closest keypoint against the radii, `observation.distance_level`, the rule the estimator
  applies to each skeleton), so the colour changes the moment a hand crosses a circle;
- ``closest``: the closest keypoint, the segment from p to it and its distance;
- ``panel``: text above the robot: the epoch and its action, red and marked FAIL-SAFE with the
  decision node's reasons when the robot failed safe; then the distance level d_k the decision
  used, the three most likely (em, ea) of the belief, and the task state.

With the arm (`cell_view_node` `robot: true`, docs/ROBOT.md) the picture is the cell with the
arm instead of the circles around p, whose bands no longer say d:

- ``arm``: the arm's link capsules at its latest joint state, each its axis drawn as a line as
  wide as the capsule with a sphere at either end;
- ``ssm_shell``: S_p as a translucent shell around the links: each capsule widened by the
  protective separation distance S_p of the arm's current speed (`hrc/separation`), so the
  person's body must stay outside it;
- ``body``: the person's body capsules (over the skeleton's bones), in the colour of the band
  of the separation S, their keypoints as before;
- ``separation``: the segment between the two closest points (on the arm, on the body), with
  S and S_p.

`CellView` is the node's state: its inputs, fed in publication order, make one consistent epoch
record (epoch, action, belief, d_k, task state, fail-safe reasons) and the latest skeleton.

Nothing is drawn beyond the cell: keypoints that are not finite or lie farther than
`observation.MAX_KEYPOINT_RANGE` from the frame's origin are left out of the picture (the
conversion refuses such skeletons; the view does not rely on it), so no marker is ever
placed at 1e308.

Nothing old is shown as current: a skeleton older than `SKELETON_STALE_S` is no longer drawn
(nobody in view, or the tracker stopped: the panel says for how long), and an action older than
`ACTION_STALE_S` is greyed with its age (the decision node stopped or the clock stalled).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..model import TASK_VARIABLES
from ..decision.observation import (MAX_KEYPOINT_RANGE, closest_distance, distance_level,
                                    level_of_distance)

LEVEL_COLORS = {0: (0.85, 0.1, 0.1), 1: (1.0, 0.5, 0.0), 2: (0.95, 0.8, 0.1),
                3: (0.2, 0.7, 0.3)}
LEVEL_NAMES = {0: 'collision', 1: 'inner', 2: 'middle', 3: 'outer'}
DISC_ALPHA = 0.25
DISC_THICKNESS = 0.004
TEXT_HEIGHT = 0.08
KEYPOINT_SIZE = 0.06
PANEL_HEIGHT = 1.6        # metres above p: the action line; the state text below it
SKELETON_STALE_S = 1.0    # a skeleton older than this is not drawn (nobody, or no tracker)
ACTION_STALE_S = 3.0      # an action older than this is greyed with its age (no decision node)
WHITE = (1.0, 1.0, 1.0, 1.0)
GREY = (0.6, 0.6, 0.6, 1.0)
KINDS = ('disc', 'sphere', 'spheres', 'line', 'text')


@dataclass(frozen=True)
class Shape:
    """One marker: `kind` in KINDS, `points` (n, 3) (a disc, sphere or text: its centre), scale
    (x, y, z) as visualization_msgs reads it for that kind, colour (r, g, b, a)."""

    ns: str
    id: int
    kind: str
    points: np.ndarray
    scale: tuple
    color: tuple
    text: str = ''


@dataclass
class CellState:
    """What the view knows of the current epoch."""

    epoch: int = 0
    action: str | None = None
    faults: str = ''                    # the decision node's fail-safe reasons, '' if none
    belief: np.ndarray | None = None    # (9,) over h = 3 em + ea
    distance_level: int | None = None   # d_k, hrc/distance_level
    task_state: dict | None = None
    keypoints: np.ndarray | None = None  # (n, 3), robot frame, the latest skeleton
    skeleton_age: int | None = None     # whole seconds since the last skeleton, once stale
    action_age: int | None = None       # whole seconds since the last action, once stale
    arm: tuple | None = None            # the arm's capsules: (segments (n, 2, 3), radii (n,))
    body: tuple | None = None           # the person's capsules, the same form
    separation: dict | None = None      # hrc/separation: S, arm / human points, S_p (m)


def with_alpha(rgb, alpha: float = 1.0) -> tuple:
    return tuple(float(c) for c in rgb) + (float(alpha),)


def fail_safe(state: CellState) -> bool:
    """dn because the decision node failed safe: it said why, or d_k = 0 forces dn."""
    return state.action == 'dn' and (bool(state.faults) or state.distance_level == 0)


def top_beliefs(belief, n: int = 3) -> list[tuple[int, int, float]]:
    """The n most likely (em, ea, probability), most likely first (ties: lower h first)."""
    b = np.asarray(belief, dtype=float).reshape(-1)
    order = sorted(range(b.size), key=lambda h: (-b[h], h))[:n]
    return [(h // 3, h % 3, float(b[h])) for h in order]


def action_line(state: CellState) -> str:
    if state.action is None:
        return f'epoch {state.epoch}: no action yet' if state.epoch else 'waiting for epoch 1'
    line = f'epoch {state.epoch}: {state.action}'
    if fail_safe(state):
        line += f'  FAIL-SAFE: {state.faults or "d = 0 (collision)"}'
    if state.action_age is not None:
        line += f'  (no action for {state.action_age} s)'
    return line


def state_text(state: CellState) -> str:
    d = state.distance_level
    lines = [f'd_k {d} ({LEVEL_NAMES[d]})' if d is not None else 'd_k none yet']
    if state.skeleton_age is not None:
        lines.append(f'skeleton: none for {state.skeleton_age} s')
    if state.belief is None:
        lines.append('belief: none yet')
    else:
        lines.append('belief (em, ea): ' + '  '.join(
            f'({em}, {ea}) {p:.2f}' for em, ea, p in top_beliefs(state.belief)))
    if state.task_state is None:
        lines.append('task: none yet')
    else:
        t = state.task_state
        lines.append(' '.join(f'{n} {t[n]}' for n in TASK_VARIABLES[:4]) + ' | '
                     + ' '.join(f'{n} {t[n]}' for n in TASK_VARIABLES[4:]))
    return '\n'.join(lines)


def drawable(keypoints) -> np.ndarray:
    """The keypoints (n, 3) inside the cell: finite and within `MAX_KEYPOINT_RANGE` of the
    frame's origin (module docstring)."""
    if keypoints is None:
        return np.zeros((0, 3))
    points = np.asarray(keypoints, dtype=float).reshape(-1, 3)
    with np.errstate(invalid='ignore'):
        inside = np.isfinite(points).all(axis=1) \
            & (np.abs(points) <= MAX_KEYPOINT_RANGE).all(axis=1)
    points = points[inside]
    return points[np.sqrt((points ** 2).sum(axis=1)) <= MAX_KEYPOINT_RANGE]


ARM_COLOR = (0.55, 0.6, 0.7)
SHELL_ALPHA = 0.12
BODY_ALPHA = 0.6


def capsules(ns: str, capsules_: tuple, color: tuple, grow: float = 0.0) -> list[Shape]:
    """Capsules (segments (n, 2, 3), radii (n,)) as markers: per capsule its axis as a line
    of the capsule's width and a sphere of that diameter at either end; `grow` widens each by
    that many metres (the S_p shell)."""
    segments, radii = capsules_
    shapes = []
    for i, (segment, radius) in enumerate(zip(np.asarray(segments, dtype=float),
                                              np.asarray(radii, dtype=float))):
        if not np.isfinite(segment).all() or np.abs(segment).max() > MAX_KEYPOINT_RANGE:
            continue
        width = 2.0 * (float(radius) + grow)
        shapes += [Shape(ns, 2 * i, 'line', segment, (width, 0.0, 0.0), color),
                   Shape(ns, 2 * i + 1, 'spheres', segment, (width, width, width), color)]
    return shapes


def arm_scene(state: CellState, radii) -> list[Shape]:
    """The arm, its S_p shell, the person's body and the separation (module docstring)."""
    shapes = capsules('arm', state.arm, with_alpha(ARM_COLOR))
    sep = state.separation
    level = None
    if sep is not None and np.isfinite(sep['S']):
        level = level_of_distance(sep['S'], radii)
        if sep['S_p'] > 0:
            shapes += capsules('ssm_shell', state.arm, with_alpha(LEVEL_COLORS[0], SHELL_ALPHA),
                               grow=float(sep['S_p']))
        ends = np.vstack([sep['arm'], sep['human']])
        if np.isfinite(ends).all() and np.abs(ends).max() <= MAX_KEYPOINT_RANGE:
            color = with_alpha(LEVEL_COLORS[level])
            shapes += [
                Shape('separation', 0, 'line', ends, (0.01, 0.0, 0.0), color),
                Shape('separation', 1, 'spheres', ends, (0.04, 0.04, 0.04), color),
                Shape('separation', 2, 'text', (ends.mean(axis=0) + [0.0, 0.0, 0.12])[None],
                      (0.0, 0.0, TEXT_HEIGHT), WHITE,
                      f'S {sep["S"]:.2f} m ({LEVEL_NAMES[level]})  S_p {sep["S_p"]:.2f} m'),
            ]
    color = LEVEL_COLORS[level] if level is not None else GREY[:3]
    if state.body is not None:
        shapes += capsules('body', state.body, with_alpha(color, BODY_ALPHA))
    keypoints = drawable(state.keypoints)
    if len(keypoints):
        shapes.append(Shape('human', 0, 'spheres', keypoints,
                            (KEYPOINT_SIZE, KEYPOINT_SIZE, KEYPOINT_SIZE), with_alpha(color)))
    return shapes


def scene(state: CellState, radii, reference_point) -> list[Shape]:
    """The whole picture of `state` (module docstring)."""
    p = np.asarray(reference_point, dtype=float).reshape(3)
    r = [float(x) for x in radii]
    if state.arm is not None:
        return arm_scene(state, r) + panel(state, p)
    shapes = []
    for i, radius in enumerate(r):    # collision on top of inner on top of middle
        shapes.append(Shape('safety', i, 'disc', (p + [0.0, 0.0, (2 - i) * DISC_THICKNESS])[None],
                            (2 * radius, 2 * radius, DISC_THICKNESS),
                            with_alpha(LEVEL_COLORS[i], DISC_ALPHA)))
    shapes.append(Shape('robot', 0, 'sphere', p[None], (0.08, 0.08, 0.08), GREY))
    keypoints = drawable(state.keypoints)
    if len(keypoints):
        level = distance_level(keypoints, p, r)
        color = with_alpha(LEVEL_COLORS[level])
        shapes.append(Shape('human', 0, 'spheres', keypoints,
                            (KEYPOINT_SIZE, KEYPOINT_SIZE, KEYPOINT_SIZE), color))
        closest = keypoints[np.argmin(np.linalg.norm(keypoints - p, axis=1))]
        distance = closest_distance(keypoints, p)
        shapes += [
            Shape('closest', 0, 'sphere', closest[None], (0.1, 0.1, 0.1), color),
            Shape('closest', 1, 'line', np.vstack([p, closest]), (0.01, 0.0, 0.0), color),
            Shape('closest', 2, 'text', (closest + [0.0, 0.0, 0.15])[None],
                  (0.0, 0.0, TEXT_HEIGHT), WHITE,
                  f'{distance:.2f} m ({LEVEL_NAMES[level]})'),
        ]
    return shapes + panel(state, p)


def panel(state: CellState, p: np.ndarray) -> list[Shape]:
    """The text above the robot: the epoch and its action, then the state."""
    return [
        Shape('panel', 0, 'text', (p + [0.0, 0.0, PANEL_HEIGHT])[None],
              (0.0, 0.0, 1.5 * TEXT_HEIGHT),
              with_alpha(LEVEL_COLORS[0]) if fail_safe(state)
              else GREY if state.action_age is not None else WHITE, action_line(state)),
        Shape('panel', 1, 'text', (p + [0.0, 0.0, PANEL_HEIGHT - 0.35])[None],
              (0.0, 0.0, TEXT_HEIGHT), WHITE, state_text(state)),
    ]


STAGED = ('belief', 'distance_level', 'task_state')


@dataclass
class CellView:
    """What the view draws, fed its inputs in publication order.

    The panel shows the last epoch that has an action, with that epoch's own inputs: after
    hrc/epoch k, the belief, distance level and task state are held (`pending`) until a_k
    arrives and then shown with it, so a picture never pairs epoch k's action with epoch k+1's
    belief. The decision node's report of the shown epoch adds its fail-safe reasons. Skeletons
    are shown as they come. `changed` says that the next refresh must draw."""

    state: CellState = field(default_factory=CellState)
    pending: dict = field(default_factory=dict)
    changed: bool = True            # the first picture, at the first refresh
    skeleton_s: float | None = None  # when the latest skeleton / action came (`now`, seconds)
    action_s: float | None = None

    def feed(self, name: str, value, now: float | None = None) -> None:
        """One input: 'epoch', 'action' (its name), 'belief', 'distance_level', 'task_state',
        'skeleton' (keypoints), 'decision' ((epoch, action, faults) of its per-epoch status),
        with the arm 'arm' and 'body' (capsules) and 'separation' (hrc/separation);
        `now` (seconds, any monotonic clock) is when it came, for `age`."""
        if name == 'skeleton':
            self.skeleton_s, self.state.skeleton_age = now, None
        elif name == 'action':
            self.action_s, self.state.action_age = now, None
        if name == 'epoch':
            self.pending = {'epoch': value}
        elif name in STAGED:
            self.pending[name] = value
        elif name == 'action':
            self.state.epoch = self.pending.get('epoch', self.state.epoch)
            self.state.action, self.state.faults = value, ''
            for key in STAGED:
                if key in self.pending:
                    setattr(self.state, key, self.pending[key])
            self.pending = {}
            self.changed = True
        elif name == 'skeleton':
            self.state.keypoints = value
            self.changed = True
        elif name in ('arm', 'body', 'separation'):
            setattr(self.state, name, value)
            self.changed = True
        elif name == 'decision':
            epoch, action, faults = value
            faults = '' if faults in ('', 'none') else faults
            if (epoch, action) == (self.state.epoch, self.state.action) \
                    and faults != self.state.faults:
                self.state.faults = faults
                self.changed = True
        else:
            raise ValueError(f'unknown view input {name!r}')

    def age(self, now: float) -> None:
        """At a refresh: stop drawing a stale skeleton, grey a stale action (module docstring);
        `changed` when what the panel says changes (once a second at most)."""
        if self.skeleton_s is not None and now - self.skeleton_s > SKELETON_STALE_S:
            age = int(now - self.skeleton_s)
            if self.state.keypoints is not None or age != self.state.skeleton_age:
                self.state.keypoints, self.state.skeleton_age = None, age
                self.state.body = self.state.separation = None
                self.changed = True
        if self.action_s is not None and now - self.action_s > ACTION_STALE_S:
            age = int(now - self.action_s)
            if age != self.state.action_age:
                self.state.action_age = age
                self.changed = True

    def drawn(self) -> None:
        self.changed = False
