"""The cell with the arm as a batch: seeded episodes in physical units (hrc-evaluate --cell arm).

The same core modules as the ROS graph with the arm (phase 2): the task book, the simulated
human (`cell.human`: hidden emotions, answers, Delta, O) with a body (`cell.person`), the belief
filter and the selectors, the robot bridge (`bridge.Bridge`: actions into trajectories under
SSM), the MuJoCo arm and a scaled trajectory controller (`arm.TrajectoryFollower`). One
episode runs the epoch protocol of docs/DESIGN.md with a physical epoch in between:

1. ``book.begin_epoch(k)``; the distance level d_k is the band (`safety_radii`, the
   estimator's rule `observation.level_of_distance`) of the separation between the arm's links
   and the latest skeleton the bridge holds, not of a reference point;
2. a_k from (b_k, x_k) by the selector (the d = 0 fail-safe applies, except to the baselines);
3. the human reacts (`SimulatedHuman.react`: acceptance, Delta, em', ea', O'); the person's
   approach level moves by Delta and their walking speed follows em', ea';
4. for `epoch_period` seconds, every `control_period`: the person walks, a skeleton frame is
   captured at `skeleton_rate` and reaches the bridge `skeleton_latency` later, the bridge
   ticks on the arm's joint state and the controller follows its trajectory and override;
5. ``book.apply(a_k, accepted, robot_runs)`` with the **physical progress rule**: the robot's
   counter bc falls this epoch only if its program completed a cycle that bc has not counted
   yet (`bridge.Progress`); b_{k+1} = update(b_k, a_k, O').

**Physical progress** (what "a task done" means here). The robot's share of a task of tc
epochs is tc cycles of its nature's program (0.9 s each at full speed); the share is done when
the last cycle completes, so SSM slow-downs, holds (dn), detours to the retreat or the
collaboration pose (dp, dm) and the approach to the program's station all delay it, for
ssm_only and for the decision layer alike. MODEL.md 3.2's bookkeeping is kept: bc falls by at
most one per epoch (never in the commit epoch, where it is set to tc), the task completes when
every committed agent's counter is 0, and the human's counter hc runs as the model says (the
person's work is not simulated physically). At full speed from the program's station the
robot's share takes exactly the model's epochs.

**The baseline `ssm_only`**: what a cell without this project runs, SSM alone. The arm always
works on the next task at the speed SSM allows: ct whenever the task is the robot's to take
(tx 0 or 2), nw while committed; it never motivates (mh), never moves away or closer (dp, dm),
never holds (dn), and has no d = 0 fail-safe (SSM stops the arm). Tasks only the person can do
(tx 1) or that need both (tx 3) go to the person through the work plan, which in the model's
terms is the only way a person commits: rh1 / rh2 every epoch until taken (with the model's
acceptance odds and its effect on the emotions).

**The baseline `integrator`**: the best simple rule an integrator would write on top of SSM
(`integrator_action`, docs/ROBOT.md 4): ssm_only's work plan, except that a task either agent
can do (tx 2) goes to the person. Like ssm_only it is outside the decision layer: no belief, no
model, no d = 0 fail-safe of its own (SSM stops the arm).

**Metrics per episode** (then mean, 95% interval, paired differences on common random numbers:
episode e of every selector sees the same task stream, the same human uniforms and the same
person's walk, `evaluation.episodes_of`; the definitions are `metrics`', which the operator's
console counts with too): tasks completed per hour of cell time; the share of
time the arm is idle (at rest, no protective stop) and in a protective stop; the minimum
separation (m) over every control sample; ssm violations, samples where the arm moved (its
speed bound s v_nominal above 1 mm/s) while the true separation (the person's body now, not
the delayed skeleton) was below S_p at that speed (ISO/TS 15066's formula: must be 0); refused
requests (eligible rh1 / rh2 answered no). Also kept: contacts (samples at S <= 0 while the
arm moved) and speed-bound breaches (samples where the links' true top speed exceeded the
bound SSM was given, which would make the check meaningless: must be 0).
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field, fields

import numpy as np

from ..cell.human import SimulatedHuman
from ..cell.scenarios import check_scenario, make_scene
from ..cell.tracking import K4ABT_JOINTS
from ..decision.observation import DEFAULT_SAFETY_RADII, level_of_distance
from ..decision.selection import ActionSelector
from ..mdp.policy import policy_arrays
from ..model import ACTIONS, CT, DN, NW, RH1, RH2, TASK_VARIABLES, HRCModel
from ..pomdp.belief import BeliefFilter
from ..study.evaluation import Z95, episodes_of
from ..study.simulation import SIMULATION_SELECTORS
from ..tasks import TaskBook, robot_cycle_done
from .arm import Arm, TrajectoryFollower, body_capsules
from .bridge import Bridge, load_programs, load_robot_description
from .metrics import IDLE, STOP, arm_activity, per_hour, request_refused, share
from .ssm import MOVING_SPEED, protective_distance

CELL_SELECTORS = ('ssm_only',) + SIMULATION_SELECTORS + ('integrator',)
DEFAULT_SELECTORS = ('ssm_only', 'paper', 'qmdp', 'integrator')
BASELINES = ('ssm_only', 'integrator')     # rules on top of SSM, outside the decision layer
METRICS = (
    ('tasks_per_hour', 'tasks per hour'),
    ('idle_share', 'robot idle %'),
    ('stop_share', 'protective stop %'),
    ('min_separation', 'min separation m'),
    ('ssm_violations', 'ssm violations'),
    ('refused_requests', 'refused requests'),
)
SPEED_SLACK = 1e-6      # m/s a link may exceed its bound by rounding


def ssm_only_action(task) -> int:
    """The ssm_only baseline's action for the task state (see the module docstring)."""
    tp, tx, ty = int(task['tp']), int(task['tx']), int(task['ty'])
    if tp > 0 and ty == 0:
        return {0: CT, 2: CT, 1: RH1, 3: RH2}[tx]
    return NW


def integrator_action(task) -> int:
    """The integrator baseline (docs/ROBOT.md 4, "the integrator's rule"): ssm_only's work
    plan, except that a task either agent can do (tx 2) goes to the person (rh1, asked every
    epoch until taken, as the plan asks for the person's own tasks) instead of the arm. In
    this cell the arm is slower than the person at every band (SSM slows it whenever the
    person is near), so of the integrator's candidate rules (hand it over when the person is
    near, d <= 1 or d <= 2, or always) the pilot run (seed 1, never the evaluation's) found
    this one best for tasks per hour. No memory, no model of the person."""
    tp, tx, ty = int(task['tp']), int(task['tx']), int(task['ty'])
    if tp > 0 and ty == 0 and tx == 2:
        return RH1
    return ssm_only_action(task)


@dataclass(frozen=True)
class ArmCellSettings:
    """The physical epoch (seconds, metres, hertz; docs/ROBOT.md)."""

    epoch_period: float = 1.0
    control_period: float = 0.02
    skeleton_rate: float = 30.0
    skeleton_latency: float = 0.05
    safety_radii: tuple = DEFAULT_SAFETY_RADII
    # s the bridge and the arm run before epoch 1, the person standing and no action yet (the
    # bridge holds): 0 starts the bridge at t = 0 in SSM's start-up protective stop, which
    # clears after resume_time. A graph's bridge is up before the decision node's first epoch
    # (docs/ROBOT.md, "the graph with the arm"): compare with one with a pre-roll of 1 s.
    pre_roll: float = 0.0
    # s from the bridge's override to the controller's motion, which the bridge plans for: the
    # batch's controller takes each override in the step it is sent (0); the graph's cobot_sim
    # over DDS, up to its override watchdog (the description's command_latency).
    command_latency: float = 0.0

    def __post_init__(self):
        for name in ('epoch_period', 'control_period', 'skeleton_rate'):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f'{name} must be a positive number, got {value!r}')
        if not (isinstance(self.pre_roll, (int, float)) and 0 <= self.pre_roll <= 60.0):
            raise ValueError(f'pre_roll must lie in [0, 60] s, got {self.pre_roll!r}')
        if not (isinstance(self.command_latency, (int, float))
                and 0 <= self.command_latency < 1.0):
            raise ValueError(f'command_latency must lie in [0, 1) s, got '
                             f'{self.command_latency!r}')
        if not 0 <= self.skeleton_latency < 1.0:
            raise ValueError(f'skeleton_latency must lie in [0, 1) s, got '
                             f'{self.skeleton_latency!r}')
        steps = self.epoch_period / self.control_period
        if abs(steps - round(steps)) > 1e-9:
            raise ValueError(f'epoch_period {self.epoch_period} s must be a whole number of '
                             f'control periods ({self.control_period} s)')

    @property
    def steps_per_epoch(self) -> int:
        return int(round(self.epoch_period / self.control_period))


# The batch cell as the ROS graph with the simulated arm runs it (`hrc-case-study --robot sim`,
# docs/ROBOT.md "the graph with the arm"): cell_sim streams skeletons at its sensor_rate, 50 Hz,
# that reach the bridge over one DDS hop (a few ms on one host), and the bridge is up before
# the decision node's first epoch. The agreement test compares a graph run with this.
GRAPH_SETTINGS = ArmCellSettings(skeleton_rate=50.0, skeleton_latency=0.005, pre_roll=1.0,
                                 command_latency=load_robot_description().command_latency)


@dataclass
class EpisodeResult:
    """One episode's metrics (module docstring) and, per epoch, what happened."""

    tasks_completed: int
    tasks_released: int
    seconds: float
    idle_time: float
    stop_time: float
    min_separation: float
    ssm_violations: int
    contacts: int
    speed_breaches: int
    refused_requests: int
    requests: int
    actions: list = field(default_factory=list)
    distances: list = field(default_factory=list)       # d_k
    separations: list = field(default_factory=list)     # S at the epoch boundary (m)
    accepted: list = field(default_factory=list)
    task_states: list = field(default_factory=list)     # x_k's task part (8 values)
    violations: list = field(default_factory=list)      # (t, S, bound, bridge's S, override)
    samples: list = field(default_factory=list)         # (t, stop, speed bound, S) per sample
    completed: list = field(default_factory=list)       # tasks completed after each epoch
    arm_path: list = field(default_factory=list)        # (t, q (6,)) every control period
    # The person scenario's figures (docs/ROBOT.md 4, "People who test SSM"):
    min_margin: float = math.inf          # min of S - S_p(bound) over the samples the arm moved
    appearance_violations: int = 0        # samples from a person's appearance until rest
    event: float = math.nan               # s: when the scenario's event started
    rest_after_event: float = math.nan    # s from the event until the arm was at rest
    stop_delay: float = math.nan          # s from the appeared person's skeleton to the stop
    monitor: dict = field(default_factory=dict)   # the bridge's monitor counts (Bridge.counts)


@dataclass
class ArmResult:
    """Per-episode metrics of one selector (arrays of length E)."""

    selector: str
    tasks_per_hour: np.ndarray
    idle_share: np.ndarray
    stop_share: np.ndarray
    min_separation: np.ndarray
    ssm_violations: np.ndarray
    refused_requests: np.ndarray
    contacts: np.ndarray
    speed_breaches: np.ndarray
    tasks_completed: np.ndarray
    # The person scenario's figures per episode (EpisodeResult; NaN where none applies).
    min_margin: np.ndarray = field(default_factory=lambda: np.zeros(0))
    appearance_violations: np.ndarray = field(default_factory=lambda: np.zeros(0))
    rest_after_event: np.ndarray = field(default_factory=lambda: np.zeros(0))
    stop_delay: np.ndarray = field(default_factory=lambda: np.zeros(0))
    seconds: float = 0.0        # compute time of the selector's episodes
    simulated: float = 0.0      # simulated cell time (s)


class ArmCell:
    """Runs episodes of the cell with the arm (see the module docstring)."""

    def __init__(self, model: HRCModel, policy, value=None, mode: str | None = None,
                 pomdp=None, description=None, programs=None,
                 settings: ArmCellSettings | None = None, person: str = 'honest'):
        self.model = model
        self.policy, self.value = policy_arrays(policy, value)
        self.pomdp = pomdp
        self.mode = mode
        self.filter = BeliefFilter(model, mode=mode)
        self.description = description or load_robot_description()
        self.programs = programs or load_programs(self.description)
        self.settings = settings or ArmCellSettings()
        self.person = check_scenario(person)
        self.arm = Arm()
        self._peaks: dict = {}
        self._choosers: dict = {}

    def _chooser(self, selector: str):
        if selector not in self._choosers:
            self._choosers[selector] = ActionSelector(self.model, self.policy, self.value,
                                                      method=selector, pomdp=self.pomdp)
        return self._choosers[selector]

    def _decide(self, selector: str, belief, x, hidden, level: int = 0) -> int:
        """The epoch's action; `level` the tasks waiting as the robot observes them, l =
        min(waiting, L) (MODEL.md 8.1, read only by a model with a queue)."""
        if selector in BASELINES:
            rule = ssm_only_action if selector == 'ssm_only' else integrator_action
            return rule(dict(zip(TASK_VARIABLES, x[:-1])))
        if selector == 'mdp':
            action = int(self.policy[level * self.model.n_base + self.model.index(hidden + x)])
        else:
            seen = x if self.model.queue is None else x + (level,)
            action = int(self._chooser(selector).select(belief, seen).action)
        return DN if x[-1] == 0 else action

    def episode(self, scenario, human_seed, person_seed, selector: str = 'paper',
                record: bool = False, actions: Sequence[str] | None = None) -> EpisodeResult:
        """One seeded episode (scenario as `evaluation.random_scenarios` makes them).

        `actions`: the robot's actions epoch by epoch (names, one per epoch) instead of the
        selector's: a recorded run's, to follow the arm and the person under the commands
        that run gave (the graph's, where it read a distance at a safety radius otherwise
        than the batch). They are taken as given: the d = 0 fail-safe is the recorded run's
        (it chose dn there or not), and the selector is only checked, not asked."""
        if selector not in CELL_SELECTORS:
            raise ValueError(f'unknown selector {selector!r}; expected one of '
                             f'{", ".join(CELL_SELECTORS)}')
        if actions is not None and (len(actions) != scenario.epochs
                                    or not set(actions) <= set(ACTIONS)):
            raise ValueError(f'actions must name one of {", ".join(ACTIONS)} for each of the '
                             f'{scenario.epochs} epochs')
        model, cfg, desc = self.model, self.settings, self.description
        em, ea, *task_values, d0 = (int(v) for v in scenario.initial_state)
        book = TaskBook(model, initial_task=dict(zip(TASK_VARIABLES, task_values)),
                        schedule=scenario.schedule)
        human = SimulatedHuman(model, seed=human_seed, em=em, ea=ea, d=d0)
        scene = make_scene(self.person, d0, person_seed, em=em, ea=ea, radii=cfg.safety_radii,
                           duration=scenario.epochs * cfg.epoch_period)
        bridge = Bridge(desc, self.programs, self.arm, cfg.control_period,
                        latency=cfg.command_latency)
        bridge._peaks = self._peaks
        follower = TrajectoryFollower(desc.poses['home'], desc.ssm.deceleration)
        arm, names, ssm = self.arm, desc.joint_names, desc.ssm
        dt = cfg.control_period
        frame_interval = 1.0 / cfg.skeleton_rate
        latency = cfg.skeleton_latency
        belief = self.filter.initial(human.observation)
        observation = human.observation

        def probe(keypoints):
            sep = arm.separation(follower.q, body_capsules(keypoints, K4ABT_JOINTS))
            return sep.distance, sep.arm_point

        first = body_capsules(scene.frame(0.0), K4ABT_JOINTS)
        pre = int(round(cfg.pre_roll / dt))
        for n in range(-pre, 0):       # the pre-roll: the person stands, the bridge holds
            now = _ns(n * dt)
            bridge.skeleton(body_capsules(scene.frame(n * dt), K4ABT_JOINTS),
                            _ns(n * dt - latency), now)
            bridge.joint_state(names, follower.q, follower.qd, now, now)
            follower.step(dt, bridge.tick(now).override)
        # The skeleton the bridge holds at t = 0: captured `latency` before the start.
        bridge.skeleton(first, _ns(-latency), 0)
        held = first
        frames: deque = deque()
        next_capture = frame_interval - latency
        out = EpisodeResult(0, 0, 0.0, 0.0, 0.0, math.inf, 0, 0, 0, 0, 0)
        out.event = scene.event if self.person != 'honest' else math.nan
        true_separation = arm.distance(follower.q, first)
        last = None
        step = 0
        appeared_frame = None         # when the first frame with the appeared person arrived
        appearance_open = False       # from the appearance until the arm is at rest
        for k in range(1, scenario.epochs + 1):
            book.begin_epoch(k)
            t = step * dt
            boundary = arm.distance(follower.q, held)
            d = level_of_distance(boundary, cfg.safety_radii)
            x = book.observable(d)
            level = 0 if model.queue is None else min(len(book.queue), model.queue_length)
            action = (self._decide(selector, belief, x, (human.em, human.ea), level)
                      if actions is None else ACTIONS.index(actions[k - 1]))
            task_before = book.state
            reaction = human.react(action, task_before)
            scene.begin_epoch(reaction.delta, reaction.em, reaction.ea, true_separation)
            now = _ns(t)
            bridge.task_state(task_before, now)
            bridge.action(action, now)
            if reaction.accepted is not None:
                out.requests += 1
                out.refused_requests += request_refused(reaction.accepted)
            if record:
                out.actions.append(ACTIONS[action])
                out.distances.append(d)
                out.separations.append(boundary)
                out.accepted.append(reaction.accepted)
                out.task_states.append(tuple(task_before[n] for n in TASK_VARIABLES))
            for _ in range(cfg.steps_per_epoch):
                t = step * dt
                now = _ns(t)
                body = body_capsules(scene.bodies(), K4ABT_JOINTS)
                if t >= next_capture - 1e-9:
                    seen = scene.frame(t)
                    if seen is not None:
                        frames.append((t, seen))
                    next_capture += frame_interval
                while frames and frames[0][0] + latency <= t + 1e-9:
                    stamp, seen = frames.popleft()
                    held = body_capsules(seen, K4ABT_JOINTS)
                    bridge.skeleton(held, _ns(stamp), now)
                    if appeared_frame is None and scene.appeared is not None \
                            and len(seen) > len(K4ABT_JOINTS):
                        # The first frame with the person who appeared: the time to the stop
                        # counts from here when they are inside S_p(0) (no motion allowed).
                        inside = arm.distance(follower.q, body_capsules(scene.bodies(),
                                                                       K4ABT_JOINTS))
                        appeared_frame = t if inside < protective_distance(0.0, inside, ssm) \
                            else -1.0
                if record:
                    out.arm_path.append((t, follower.q.copy()))
                # The truth at t: every body in the cell now, the arm's speed bound now.
                true_separation = arm.distance(follower.q, body)
                bound = follower.speed_bound
                out.min_separation = min(out.min_separation, true_separation)
                if scene.appeared is not None and not appearance_open \
                        and math.isnan(out.rest_after_event):
                    appearance_open = True
                if bound > MOVING_SPEED:
                    margin = true_separation - protective_distance(bound, true_separation, ssm)
                    if not appearance_open:
                        out.min_margin = min(out.min_margin, margin)
                    if margin < 0.0:
                        if appearance_open:
                            out.appearance_violations += 1
                        else:
                            out.ssm_violations += 1
                            if record:
                                out.violations.append((t, true_separation, bound, last))
                    if true_separation <= 0.0:
                        out.contacts += 1
                    if arm.link_speed(follower.q, follower.qd) > bound + SPEED_SLACK:
                        out.speed_breaches += 1
                elif t >= out.event and math.isnan(out.rest_after_event) \
                        and (not scene.appears or appeared_frame is not None):
                    # at rest after the event; for an appeared person, after their first
                    # frame reached the bridge (an arm at rest when they appear may start
                    # again before the sensor shows them: no monitor sees them sooner)
                    out.rest_after_event = t - out.event
                    appearance_open = False
                bridge.joint_state(names, follower.q, follower.qd, now, now)
                command = bridge.tick(now)
                last = (command.separation.distance if command.separation else None,
                        command.override, command.motion, command.stop)
                if appeared_frame is not None and appeared_frame >= 0 and command.stop \
                        and math.isnan(out.stop_delay):
                    out.stop_delay = t - appeared_frame
                activity = arm_activity(command.stop, bound)
                if activity == STOP:
                    out.stop_time += dt
                elif activity == IDLE:
                    out.idle_time += dt
                if record:
                    out.samples.append((t, command.stop, bound, true_separation))
                if command.trajectory is not None:
                    follower.follow(command.trajectory)
                follower.step(dt, command.override)
                scene.step(dt, t, probe, true_separation)
                step += 1
            progress = bridge.progress
            bc = task_before['bc']
            robot_runs = progress is not None and robot_cycle_done(progress.cycles,
                                                                   progress.cycles_done, bc)
            book.apply(action, reaction.accepted, robot_runs)
            if record:
                out.completed.append(len(book.completed))
            evidence = None
            if self.filter.mode == 'posterior':
                evidence = model.transition_likelihood(action, reaction.accepted is not None,
                                                       bool(reaction.accepted), d,
                                                       level_of_distance(
                                                           arm.separation(follower.q,
                                                                          held).distance,
                                                           cfg.safety_radii))
                if not np.sum(evidence) > 0:
                    evidence = None     # a move the model calls impossible: left out
            belief = self.filter.update(belief, action, reaction.observation, evidence)
            observation = reaction.observation
        del observation
        out.seconds = scenario.epochs * cfg.epoch_period
        out.monitor = dict(bridge.counts)
        out.tasks_completed = len(book.completed)
        out.tasks_released = sum(1 for r in book.records if r.release_epoch <= scenario.epochs)
        return out


def _ns(seconds: float) -> int:
    return int(round(seconds * 1e9))


def person_seed(seed: int, episode: int) -> list:
    """Seed of episode `episode`'s person's walk (the same for every selector)."""
    return [seed, episode, 2]


def evaluate_arm(model: HRCModel, policy, episodes: int = 200, epochs: int = 50,
                 seed: int = 0, task_rate: float = 0.5, selectors=DEFAULT_SELECTORS,
                 mode: str | None = None, pomdp=None, progress=None,
                 settings: ArmCellSettings | None = None, description=None,
                 programs=None, person: str = 'honest') -> dict:
    """selector -> ArmResult over the same seeded episodes (common random numbers), with the
    person of scenario `person` (`cell.scenarios`)."""
    for s in selectors:
        if s not in CELL_SELECTORS:
            raise ValueError(f'unknown selector {s!r}; expected some of '
                             f'{", ".join(CELL_SELECTORS)}')
    scenarios, seeds = episodes_of(model, 'random', episodes, epochs, seed, task_rate)
    cell = ArmCell(model, policy, mode=mode, pomdp=pomdp, description=description,
                   programs=programs, settings=settings, person=person)
    results = {}
    for selector in selectors:
        t0 = time.process_time()
        rows = []
        for e, (scenario, human) in enumerate(zip(scenarios, seeds)):
            rows.append(cell.episode(scenario, human, person_seed(seed, e), selector))
            if progress and ((e + 1) % 50 == 0 or e + 1 == episodes):
                progress(f'{selector}: {e + 1}/{episodes} episodes '
                         f'({time.process_time() - t0:.1f} s)')
        seconds = np.array([r.seconds for r in rows])
        results[selector] = ArmResult(
            selector,
            tasks_per_hour=per_hour(np.array([r.tasks_completed for r in rows]), seconds),
            idle_share=share(np.array([r.idle_time for r in rows]), seconds),
            stop_share=share(np.array([r.stop_time for r in rows]), seconds),
            min_separation=np.array([r.min_separation for r in rows]),
            ssm_violations=np.array([r.ssm_violations for r in rows], dtype=float),
            refused_requests=np.array([r.refused_requests for r in rows], dtype=float),
            contacts=np.array([r.contacts for r in rows], dtype=float),
            speed_breaches=np.array([r.speed_breaches for r in rows], dtype=float),
            tasks_completed=np.array([r.tasks_completed for r in rows], dtype=float),
            min_margin=np.array([r.min_margin for r in rows]),
            appearance_violations=np.array([r.appearance_violations for r in rows],
                                           dtype=float),
            rest_after_event=np.array([r.rest_after_event for r in rows]),
            stop_delay=np.array([r.stop_delay for r in rows]),
            seconds=time.process_time() - t0,
            simulated=float(np.sum(seconds)))
    return results


# -- statistics and the table ------------------------------------------------------------------
def _interval(x: np.ndarray) -> dict:
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    mean = float(x.mean()) if x.size else float('nan')
    half = float(Z95 * x.std(ddof=1) / math.sqrt(x.size)) if x.size > 1 else float('nan')
    return {'n': int(x.size), 'mean': mean, 'half_width': half, 'low': mean - half,
            'high': mean + half}


def summarize_arm(result: ArmResult) -> dict:
    """metric -> {n, mean, half_width, low, high}: a 95% normal interval over episodes."""
    return {metric: _interval(getattr(result, metric)) for metric, _ in METRICS}


def paired_arm(result: ArmResult, reference: ArmResult) -> dict:
    """metric -> the paired (same episodes) difference result - reference, 95% interval."""
    return {metric: _interval(getattr(result, metric) - getattr(reference, metric))
            for metric, _ in METRICS}


def format_arm_table(results: dict) -> str:
    """Mean ± 95% half-width per selector and metric."""
    width = 20
    head = f'{"selector":<9}' + ''.join(f'{label:>{width}}' for _, label in METRICS)
    lines = [head, '-' * len(head)]
    for selector, result in results.items():
        summary = summarize_arm(result)
        cells = []
        for metric, _ in METRICS:
            s = summary[metric]
            digits = 3 if metric == 'min_separation' else 2
            cells.append(f'{s["mean"]:.{digits}f} ± {s["half_width"]:.{digits}f}')
        lines.append(f'{selector:<9}' + ''.join(f'{c:>{width}}' for c in cells))
    return '\n'.join(lines)


def format_arm_paired(results: dict, baseline: str) -> str:
    """Per selector and metric, the paired difference to `baseline` with its 95% interval
    and whether the interval excludes 0."""
    reference = results[baseline]
    lines = [f'paired differences to {baseline} (same episodes, 95%):']
    for selector, result in results.items():
        if selector == baseline:
            continue
        for metric, label in METRICS:
            d = paired_arm(result, reference)[metric]
            if not math.isfinite(d['half_width']):
                verdict = ''
            elif d['low'] > 0:
                verdict = 'higher'
            elif d['high'] < 0:
                verdict = 'lower'
            else:
                verdict = 'not distinguishable'
            lines.append(f'  {selector:<9} - {baseline:<9} {label:<20} {d["mean"]:+10.3f} ± '
                         f'{d["half_width"]:.3f}  {verdict}')
    return '\n'.join(lines)


def arm_result_fields() -> tuple:
    return tuple(f.name for f in fields(ArmResult))[1:-2]


def scenario_figures(result: ArmResult, control_period: float) -> dict:
    """The person scenario's figures of one selector (docs/ROBOT.md 4, "People who test
    SSM"): SSM violations against the true bodies, the appearance exception apart, the
    smallest margin S - S_p while the arm moved, the time from the event to the arm at rest,
    and the time from an appeared person's first skeleton to the protective stop."""
    def finite(x):
        x = np.asarray(x, dtype=float)
        return x[np.isfinite(x)]
    margin, rest, delay = (finite(result.min_margin), finite(result.rest_after_event),
                           finite(result.stop_delay))
    return {
        'episodes': int(len(result.ssm_violations)),
        'ssm_violations': int(result.ssm_violations.sum()),
        'episodes_with_violations': int((result.ssm_violations > 0).sum()),
        'appearance_violations': int(result.appearance_violations.sum()),
        'contacts': int(result.contacts.sum()),
        'speed_breaches': int(result.speed_breaches.sum()),
        'min_margin_m': float(margin.min()) if margin.size else None,
        'rest_after_event_s': ({'mean': float(rest.mean()), 'p95': float(np.percentile(rest, 95)),
                                'max': float(rest.max()), 'n': int(rest.size)}
                               if rest.size else None),
        'stop_delay_periods': ({'max': float(delay.max() / control_period),
                                'n': int(delay.size)} if delay.size else None),
    }


def format_scenario_figures(results: dict, person: str, control_period: float) -> str:
    """One line per selector of `scenario_figures`."""
    lines = [f'person {person}: SSM against the true bodies']
    for selector, result in results.items():
        f = scenario_figures(result, control_period)
        rest = f['rest_after_event_s']
        delay = f['stop_delay_periods']
        margin = f['min_margin_m']
        lines.append(
            f'  {selector:<9} violations {f["ssm_violations"]} in {f["episodes"]} episodes, '
            f'appearance {f["appearance_violations"]}, contacts {f["contacts"]}, '
            f'smallest margin ' + ('-' if margin is None else f'{margin:+.3f} m')
            + ', rest after the event ' + ('-' if rest is None else
                                           f'{rest["mean"]:.2f} s (p95 {rest["p95"]:.2f}, max '
                                           f'{rest["max"]:.2f})')
            + ', stop after an appeared skeleton ' + ('-' if delay is None else
                                                      f'<= {delay["max"]:.0f} control periods'))
    return '\n'.join(lines)
