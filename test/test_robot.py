"""The robot side's core (hrc_ros/core/robot): SSM, the arm, the bridge, the cell with the arm.

- SSM (ISO/TS 15066 5.5.4): worked examples whose numbers are computed by hand in the
  comments, the closed form against a bisection of S_p itself, continuity at ISO 13855's
  0.5 m, the monitor's stops (no data, old data, too close) and its resume.
- The arm: MuJoCo's forward kinematics against a plain numpy DH chain of the published UR5e
  table; the capsule distance kernel against MuJoCo's own mj_geomDistance; link speeds against
  finite differences; the scaled trajectory controller's ramps and limits.
- The bridge: the robot description's refusals (one line each), joint-state refusals, the
  action table, the safe point, SSM below every action, the program's progress and its
  resumption after a retreat.
- The cell with the arm: the physical progress rule (model.step_task's robot_runs), the
  ssm_only baseline, 0 SSM violations and 0 speed-bound breaches in a batch, a person who
  never moves faster than SSM assumes, and `hrc-evaluate --cell arm`.
"""

from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np
import pytest

from hrc_ros.core.model import CT, DM, DN, DP, MH, NW, RH1, RH2, TASK_VARIABLES, step_task
from hrc_ros.core.robot import ssm
from hrc_ros.core.robot.arm import (JOINT_NAMES, UR5E_DH, Arm, BodyCapsules, Trajectory,
                                    TrajectoryFollower, body_capsules, segment_duration)
from hrc_ros.core.robot.bridge import (Bridge, RobotDescriptionError, load_programs,
                                       load_robot_description, programs_from,
                                       robot_description)
from hrc_ros.core.protocol import InputError

P = ssm.SsmParameters()       # the defaults: T_r 0.1 s, a 2 m/s^2, C + Z_d + Z_r = 0.11 m


# -- SSM -----------------------------------------------------------------------------------------
def test_ssm_far_worked_example():
    # S = 2.0 m, data fresh. w = S - 0.5 = 1.5 m; the walking regime holds up to
    # v_w = a (w / v_h - T_r) = 2 (0.9375 - 0.1) = 1.675 m/s.
    # Walking: A = 1/(2a) = 0.25, B = v_h / a + T_r = 0.8 + 0.1 = 0.9,
    # K = v_h T_r + M - S = 0.16 + 0.11 - 2.0 = -1.73;
    # v = a (-B + sqrt(B^2 - 2K/a)) = 2 (-0.9 + sqrt(0.81 + 1.73)) = 2 (-0.9 + 1.5937377)
    #   = 1.3874755 m/s <= 1.675: the answer.
    v = ssm.max_speed(2.0, P)
    assert v == pytest.approx(1.3874755, abs=1e-6)
    # S_p at that speed: T_s = v / a = 0.6937377; S_h = 1.6 (0.1 + 0.6937377) = 1.2699804;
    # S_r = 0.1 v = 0.1387476; S_s = v^2 / 4 = 0.4812720; + 0.11 -> 2.0000000.
    assert ssm.protective_distance(v, 2.0, P) == pytest.approx(2.0, abs=1e-6)
    # 1.4 m/s is too fast: T_s = 0.7, S_h = 1.28, S_r = 0.14, S_s = 0.49, + 0.11 = 2.02 > 2.0.
    assert ssm.protective_distance(1.4, 2.0, P) == pytest.approx(2.02, abs=1e-9)
    assert ssm.ssm_violated(2.0, 1.4, P)
    assert not ssm.ssm_violated(2.0, 1.38, P)


def test_ssm_near_worked_example():
    # S = 0.6 m: w = 0.1 m, v_w = 2 (0.1 / 1.6 - 0.1) < 0, so the person reaches (2.0 m/s)
    # after 0.0625 s of walking. B = v_near / a + T_r = 1.0 + 0.1 = 1.1;
    # K = w + v_near (T_r - w / v_h) + M - S = 0.1 + 2.0 (0.1 - 0.0625) + 0.11 - 0.6 = -0.315;
    # v = 2 (-1.1 + sqrt(1.21 + 0.315)) = 2 (-1.1 + 1.2349089) = 0.2698178 m/s.
    v = ssm.max_speed(0.6, P)
    assert v == pytest.approx(0.2698178, abs=1e-6)
    # D = 0.1 + 2.0 (0.1 + v/2 - 0.0625) = 0.4448178; S_r = 0.0269818; S_s = v^2/4 = 0.0182004;
    # + 0.11 = 0.6.
    assert ssm.human_travel(0.6, 0.1 + v / 2, P) == pytest.approx(0.4448178, abs=1e-6)
    assert ssm.protective_distance(v, 0.6, P) == pytest.approx(0.6, abs=1e-6)


def test_ssm_protective_stop_worked_example():
    # S = 0.3 m: at v = 0, S_p = v_near T_r + M = 0.2 + 0.11 = 0.31 > 0.3: no speed is safe.
    assert ssm.protective_distance(0.0, 0.3, P) == pytest.approx(0.31)
    assert ssm.max_speed(0.3, P) is None
    # S = 0.32 m: K = 0.31 - 0.32 = -0.01, v = 2 (-1.1 + sqrt(1.21 + 0.01)) = 0.0090721 m/s,
    # below min_speed (0.02): the monitor stops too ("even the slowest motion is too fast").
    assert ssm.max_speed(0.32, P) == pytest.approx(0.0090721, abs=1e-6)
    monitor = ssm.SpeedSeparationMonitor(P, period=0.0)
    state = monitor.update(0.32, 0, 0, nominal_speed=0.5)
    assert state.stop and state.override == 0.0 and 'slowest motion' in state.reason


def test_ssm_data_age_and_control_period_add_to_the_persons_time():
    # S = 2.0 m, data 0.1 s old, held 0.02 s: the person may have reached R = 2.0 (0.1 + 0.02)
    # = 0.24 m nearer unseen, S' = 1.76; T_hum = 0.1, T_rob = 0.12. B = 0.8 + 0.12 = 0.92,
    # K = 1.6 * 0.1 + 0.11 - 1.76 = -1.49; v = 2 (-0.92 + sqrt(0.8464 + 1.49)) = 2 (-0.92 +
    # 1.5285287) = 1.2170574 (v_w = 2 (1.26 / 1.6 - 0.1) = 1.375: walking regime).
    assert ssm.max_speed(2.0, P, age=0.1, period=0.02) == pytest.approx(1.2170574, abs=1e-6)
    assert ssm.protective_distance(1.2170574, 2.0, P, 0.1, 0.02) == pytest.approx(2.0, abs=1e-6)
    # A person measured coming at 2.4 m/s is planned for at that speed (ISO/TS 15066 5.5.4.2.2)
    fast = ssm.directed_speeds(P, 2.4)
    assert (fast.human_speed, fast.human_speed_near) == (2.4, 2.4)
    assert ssm.directed_speeds(P, 1.2) is P
    assert ssm.max_speed(2.0, fast) < ssm.max_speed(2.0, P)


def test_ssm_braking_speed_keeps_the_robot_able_to_follow_the_allowed_speed_down():
    # Far away the allowed speed falls slower than the robot brakes: max_speed itself.
    assert ssm.braking_speed(2.0, P) == pytest.approx(ssm.max_speed(2.0, P))
    # Near 0.5 m it falls faster (the person's assumed travel grows as S falls): the command
    # is one the robot can brake from at a to every later separation a 2.0 m/s approach gives.
    for s in np.linspace(0.33, 0.9, 40):
        v = ssm.braking_speed(s, P)
        assert v <= ssm.max_speed(s, P) + 1e-12
        for k in range(1, 21):
            later = ssm.max_speed(s - 2.0 * 0.02 * k, P) or 0.0
            assert v <= later + 2.0 * 0.02 * k + 1e-9
    assert ssm.braking_speed(0.3, P) is None
    # The look-ahead is skipped where it cannot bind (above a quarter of v_near, with a
    # margin): on a grid it binds only below that, and never with a directed speed.
    for approach in (0.0, 3.0):
        p = ssm.directed_speeds(P, approach)
        limit = ssm.BRAKING_SKIP * p.human_speed_near
        for s in np.linspace(0.3, 3.0, 120):
            for age, period in ((0.0, 0.0), (0.05, 0.04), (0.2, 0.06)):
                now = ssm.max_speed(s, p, age, period)
                if now is None:
                    continue
                full = now
                for k in range(1, 21):
                    later = ssm.max_speed(s - p.human_speed_near * 0.02 * k, p, age, period)
                    full = min(full, (later or 0.0) + p.deceleration * 0.02 * k)
                assert full == pytest.approx(now) or now < limit
                assert ssm.braking_speed(s, p, age, period) == pytest.approx(full)


def test_ssm_closed_form_matches_a_bisection_and_has_no_jump_at_half_a_metre():
    rng = np.random.default_rng(3)
    for _ in range(300):
        p = ssm.SsmParameters(reaction_time=rng.uniform(0.02, 0.4),
                              deceleration=rng.uniform(0.5, 5.0),
                              intrusion=rng.uniform(0, 0.2), human_speed=rng.uniform(1.0, 2.0),
                              human_speed_near=2.0 + rng.uniform(0, 0.5),
                              near_distance=rng.uniform(0, 1.0))
        s, age, period = rng.uniform(0.0, 3.0), rng.uniform(0, 0.2), rng.uniform(0, 0.05)
        v = ssm.max_speed(s, p, age, period)
        def f(x, s=s, p=p, age=age, period=period):
            return ssm.protective_distance(x, s, p, age, period) - s
        if f(0.0) > 0:
            assert v is None
            continue
        lo, hi = 0.0, 100.0
        for _ in range(200):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if f(mid) <= 0 else (lo, mid)
        assert v == pytest.approx(lo, abs=1e-7)
    # Continuous and increasing in S through near_distance (no switch of v_h at 0.5 m).
    below, above = ssm.max_speed(0.5 - 1e-9, P), ssm.max_speed(0.5 + 1e-9, P)
    assert above - below == pytest.approx(0.0, abs=1e-6)
    grid = [ssm.max_speed(s, P) or 0.0 for s in np.linspace(0.3, 3.0, 400)]
    assert np.all(np.diff(grid) >= 0)


def test_ssm_override_and_parameters():
    assert ssm.speed_override(0.3, 0.6) == pytest.approx(0.5)
    assert ssm.speed_override(0.3, 0.2) == 1.0
    assert ssm.speed_override(None, 0.2) == 0.0
    assert ssm.SsmParameters.from_stopping_time(0.5, 1.0).deceleration == 2.0
    for bad in ({'reaction_time': -0.1}, {'deceleration': 0.0}, {'intrusion': math.nan},
                {'human_speed_near': 1.0}):
        with pytest.raises(ValueError):
            ssm.SsmParameters(**bad)
    with pytest.raises(ValueError, match='unknown SSM parameters'):
        ssm.SsmParameters.from_mapping({'reaction': 0.1})
    # Fast robots are violations, a resting one never is.
    assert not ssm.ssm_violated(0.0, 0.0, P)
    assert list(ssm.ssm_violated(np.array([2.0, 2.0]), np.array([1.0, 1.5]), P)) == [False, True]


def test_ssm_monitor_stops_without_data_on_old_data_and_resumes_after_resume_time():
    monitor = ssm.SpeedSeparationMonitor(P, period=0.01)
    assert monitor.update(None, None, 0, 0.5).reason == 'no human data yet'
    ms = 1_000_000
    # Fresh data far away: the stop clears only after resume_time (0.2 s) of allowed motion.
    assert monitor.update(3.0, 0, 10 * ms, 0.5).stop
    assert monitor.update(3.0, 150 * ms, 150 * ms, 0.5).stop
    state = monitor.update(3.0, 220 * ms, 220 * ms, 0.5)
    assert not state.stop and state.override == 1.0
    # The same separation, older data: a lower allowed speed.
    fresh = monitor.update(1.0, 300 * ms, 300 * ms, 2.0)
    older = monitor.update(1.0, 0, 300 * ms, 2.0)
    assert older.allowed_speed < fresh.allowed_speed and older.override < fresh.override
    stale = monitor.update(1.0, 0, 600 * ms, 2.0)
    assert stale.stop and 'old' in stale.reason and 'anywhere' in stale.reason
    assert monitor.update(None, None, 700 * ms, 2.0).reason == 'no human data'


# -- the arm --------------------------------------------------------------------------------------
def dh_chain(q) -> np.ndarray:
    """The flange pose of the standard DH chain, plain numpy (independent of the MJCF)."""
    t = np.eye(4)
    for i, theta in enumerate(q):
        d, a, alpha = UR5E_DH.d[i], UR5E_DH.a[i], UR5E_DH.alpha[i]
        ct, st, ca, sa = np.cos(theta), np.sin(theta), np.cos(alpha), np.sin(alpha)
        t = t @ np.array([[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st],
                          [0, sa, ca, d], [0, 0, 0, 1]])
    return t


@pytest.fixture(scope='module')
def arm():
    return Arm()


def test_forward_kinematics_agree_with_the_dh_table(arm):
    rng = np.random.default_rng(0)
    for q in [np.zeros(6)] + [rng.uniform(-np.pi, np.pi, 6) for _ in range(50)]:
        pose = arm.forward(q)
        reference = dh_chain(q)
        np.testing.assert_allclose(pose.flange_position, reference[:3, 3], atol=1e-9)
        np.testing.assert_allclose(pose.flange_rotation, reference[:3, :3], atol=1e-9)
    # The zero pose stretches along -x: a2 + a3 = -0.8172 m, the flange d1 - d5 = 0.0628 m up,
    # d4 + d6 = 0.2329 m along -y (z1 = -y0).
    np.testing.assert_allclose(arm.forward(np.zeros(6)).flange_position,
                               [-0.8172, -0.2329, 0.0628], atol=1e-9)


def _scratch_capsules(mujoco, a, ra, b, rb):
    xml = f"""<mujoco><worldbody>
      <geom name="a" type="capsule" size="{ra}" fromto="{' '.join(map(str, a.ravel()))}"/>
      <geom name="b" type="capsule" size="{rb}" fromto="{' '.join(map(str, b.ravel()))}"/>
    </worldbody></mujoco>"""
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    fromto = np.zeros(6)
    distance = mujoco.mj_geomDistance(model, data, 0, 1, 10.0, fromto)
    return distance, fromto


def test_capsule_separation_agrees_with_mujocos_geom_distance():
    import mujoco
    from hrc_ros.core.robot.arm import separation
    rng = np.random.default_rng(1)
    for _ in range(60):
        a = rng.uniform(-0.5, 0.5, (2, 3))
        b = rng.uniform(-0.5, 0.5, (2, 3)) + rng.uniform(-0.6, 0.6, 3)
        ra, rb = rng.uniform(0.02, 0.1, 2)
        expected, fromto = _scratch_capsules(mujoco, a, ra, b, rb)
        body = BodyCapsules(b[None], np.array([rb]), ('b',))
        got = separation(a[None], np.array([ra]), ('a',), body)
        if expected > 0:
            assert got.distance == pytest.approx(expected, abs=1e-6)
            # Both points are on the surfaces, as far apart as the distance.
            assert np.linalg.norm(got.human_point - got.arm_point) == \
                pytest.approx(got.distance, abs=1e-6)
            np.testing.assert_allclose(got.arm_point, fromto[:3], atol=1e-5)
            np.testing.assert_allclose(got.human_point, fromto[3:], atol=1e-5)
        else:
            assert got.distance <= 1e-9


def test_separation_names_the_closest_pair_of_a_k4abt_body(arm):
    from hrc_ros.core.cell.person import SimulatedPerson
    from hrc_ros.core.cell.tracking import K4ABT_JOINTS
    person = SimulatedPerson(1, seed=0)
    body = body_capsules(person.keypoints(), K4ABT_JOINTS)
    assert len(body.names) == 12 and body.names[0] == 'torso'
    two = body_capsules(np.vstack([person.keypoints()] * 2), K4ABT_JOINTS)
    assert len(two.names) == 24 and two.names[12] == 'torso_1'
    q = load_robot_description().poses['collaboration']
    sep = arm.separation(q, body)
    brute = min(arm.separation(q, BodyCapsules(body.segments[[j]], body.radii[[j]],
                                               (body.names[j],))).distance
                for j in range(len(body.names)))
    assert sep.distance == pytest.approx(brute) and sep.body_part in body.names
    assert arm.distance(q, body) == pytest.approx(sep.distance)
    spheres = body_capsules(person.keypoints()[:7])
    assert np.all(spheres.radii == 0.1) and len(spheres.names) == 7
    for bad in (np.full((4, 3), np.nan), np.zeros((5, 2))):
        with pytest.raises(ValueError):
            body_capsules(bad)
    with pytest.raises(ValueError, match='whole bodies'):
        body_capsules(np.zeros((33, 3)), K4ABT_JOINTS)


def test_link_speed_bounds_every_surface_point(arm):
    from hrc_ros.core.robot._kernels import link_speed
    rng = np.random.default_rng(2)
    h = 1e-7
    for _ in range(20):
        q, qd = rng.uniform(-3, 3, 6), rng.uniform(-2, 2, 6)
        ends = arm.segments(q)
        moved = arm.segments(q + qd * h)
        axis_speed = np.linalg.norm((moved - ends) / h, axis=2).max()
        # With zero radii the kernel is the axis ends' speed, which finite differences give.
        zero = link_speed(ends, np.zeros_like(arm.radii), arm.last_joint, arm.data.xaxis,
                          arm.data.xanchor, qd)
        assert zero == pytest.approx(axis_speed, rel=1e-5)
        # Points on the capsules' surfaces (offsets r * n fixed in the moving body) are no faster.
        full = arm.link_speed(q, qd)
        pose, later = arm.forward(q), arm.forward(q + qd * h)
        for c in range(len(arm.radii)):
            for u in (0.0, 0.5, 1.0):
                normal = rng.normal(size=3)
                axis = pose.segments[c, 1] - pose.segments[c, 0]
                normal -= axis * (normal @ axis) / max(axis @ axis, 1e-12)
                normal *= arm.radii[c] / np.linalg.norm(normal)
                # The same body-fixed point at q + qd h: rotate the offset with the body.
                r_now = pose.segments[c, 0] + u * axis + normal
                rot = later_rotation(arm, q, qd, h, c)
                r_later = (later.segments[c, 0] + u * (later.segments[c, 1] - later.segments[c, 0])
                           + rot @ normal)
                assert np.linalg.norm(r_later - r_now) / h <= full * (1 + 1e-5) + 1e-9
        assert full >= axis_speed


def later_rotation(arm, q, qd, h, capsule):
    """The rotation of capsule `capsule`'s body between q and q + qd h."""
    body = arm.model.geom_bodyid[arm._geoms.start + capsule]
    arm.forward(q)
    now = arm.data.xmat[body].reshape(3, 3).copy()
    arm.forward(q + qd * h)
    later = arm.data.xmat[body].reshape(3, 3).copy()
    return later @ now.T


def test_follower_runs_the_cubic_segments_within_the_limits_and_brakes_at_the_ssm_rate(arm):
    description = load_robot_description()
    q0, q1 = description.poses['home'], description.poses['retreat']
    duration = segment_duration(q0, q1, description.velocity, description.acceleration)
    # Peak joint speed 1.5 |dq| / T and acceleration 6 |dq| / T^2 hit a limit exactly.
    dq = np.abs(q1 - q0)
    assert max(np.max(1.5 * dq / duration / description.velocity),
               np.max(6 * dq / duration ** 2 / description.acceleration)) == pytest.approx(1.0)
    traj = Trajectory(JOINT_NAMES, np.array([q0, q1]), np.array([duration]), 0.8, (-1,))
    follower = TrajectoryFollower(q0, deceleration=2.0)
    follower.follow(traj)
    dt, bounds, speeds, t = 0.005, [], [], 0.0
    while not follower.done and t < 10:
        state = follower.step(dt, 1.0)
        bounds.append(state.speed_bound)
        speeds.append(np.abs(state.qd) / description.velocity)
        t += dt
    np.testing.assert_allclose(follower.q, q1, atol=1e-12)
    assert np.max(speeds) <= 1.0 + 1e-9
    # From rest the scaling ramps at a / v_nominal: the bound rises by a dt per step at most.
    assert np.max(np.diff(bounds)) <= 2.0 * dt + 1e-9
    # Braking mid-way: the bound falls by a dt per step, then the arm stands, still on its path.
    follower.follow(Trajectory(JOINT_NAMES, np.array([q1, q0]), np.array([duration]), 0.8,
                               (-1,)))
    for _ in range(int(0.8 / dt)):
        follower.step(dt, 1.0)
    falling = [follower.step(dt, 0.0).speed_bound for _ in range(200)]
    assert np.min(np.diff(falling)) >= -2.0 * dt - 1e-9 and falling[-1] == 0.0
    assert not np.allclose(follower.q, q0) and np.all(follower.qd == 0)
    with pytest.raises(ValueError, match='start at'):
        follower.follow(traj)


# -- the robot description -----------------------------------------------------------------------
def _description_data():
    import yaml
    from hrc_ros.core.robot.bridge import shipped_robot_path
    return yaml.safe_load(shipped_robot_path().read_text())


@pytest.mark.parametrize('change, message', [
    (lambda d: d['poses'].pop('retreat'), 'missing poses retreat'),
    (lambda d: d['joints'][2].pop('velocity'), 'elbow_joint has no velocity'),
    (lambda d: d.pop('joints'), 'missing joints'),
    (lambda d: d['poses'].update(home={'shoulder_pan_joint': 0, 'gripper': 1}),
     "unknown joints ['gripper']"),
    (lambda d: d['poses'].update(home=[0, 0, 4.0, 0, 0, 0]), 'pose home: elbow_joint = 4.0000'),
    (lambda d: d['poses'].update(home=[0, 0, float('nan'), 0, 0, 0]), 'finite'),
    (lambda d: d['joints'][0].update(acceleration=-1), 'must be > 0'),
    (lambda d: d.update(collaboration_speed=2.0), 'collaboration_speed'),
    (lambda d: d['ssm'].update(reaction=0.1), 'unknown SSM parameters'),
])
def test_robot_description_refusals_are_one_line(change, message):
    data = _description_data()
    change(data)
    with pytest.raises(RobotDescriptionError) as info:
        robot_description(data, 'ur5e.yaml')
    text = str(info.value)
    assert message in text and '\n' not in text and text.startswith('ur5e.yaml: ')


def test_programs_refusals_and_file_checks(tmp_path):
    description = load_robot_description()
    programs = load_programs(description)
    assert sorted(programs) == [0, 2, 3] and programs[0].cycle_time == pytest.approx(0.9)
    good = {'programs': {n: {'waypoints': p.waypoints.tolist(), 'durations': p.durations.tolist()}
                         for n, p in programs.items()}}
    too_fast = copy.deepcopy(good)
    too_fast['programs'][0]['durations'] = [0.1, 0.45]
    with pytest.raises(RobotDescriptionError, match='shorter than the 0.42'):
        programs_from(too_fast, description)
    missing = copy.deepcopy(good)
    del missing['programs'][3]
    with pytest.raises(RobotDescriptionError, match=r'no program for natures \[3\]'):
        programs_from(missing, description)
    strange = dict(good, joints=['a', 'b', 'c', 'd', 'e', 'f'])
    with pytest.raises(RobotDescriptionError, match="unknown joints"):
        programs_from(strange, description)
    big = tmp_path / 'big.yaml'
    big.write_text('x: ' + 'a' * (1 << 20) + '\n')
    too_big = 'more than the 1,048,576 a robot description file may have'
    with pytest.raises(RobotDescriptionError, match=too_big):
        load_robot_description(big)
    listed = tmp_path / 'list.yaml'
    listed.write_text('- 1\n')
    with pytest.raises(RobotDescriptionError, match='is a mapping'):
        load_robot_description(listed)
    with pytest.raises(RobotDescriptionError, match='cannot read'):
        load_robot_description(tmp_path / 'none.yaml')


# -- the bridge ---------------------------------------------------------------------------------
MS = 1_000_000


@pytest.fixture(scope='module')
def setup(arm):
    description = load_robot_description()
    return description, load_programs(description), arm


JITTER = np.random.default_rng(2026)


def jitter(body, noise=0.0015):
    """The body as a real tracker reports a person standing still: millimetres of noise on
    every keypoint (the bridge takes a skeleton that repeats the last one exactly as a frozen
    tracker's, guard.SkeletonCheck)."""
    return BodyCapsules(body.segments + JITTER.normal(0.0, noise, body.segments.shape),
                        body.radii, body.names)


def far_body(distance=2.5):
    from hrc_ros.core.cell.person import SimulatedPerson
    from hrc_ros.core.cell.tracking import K4ABT_JOINTS
    person = SimulatedPerson(3, seed=0)
    person.rho = distance
    return jitter(body_capsules(person.keypoints(), K4ABT_JOINTS))


class Rig:
    """A bridge and a simulated controller stepped together at 100 Hz."""

    def __init__(self, setup, body=None, q=None):
        description, programs, arm = setup
        self.description = description
        self.bridge = Bridge(description, programs, arm, period=0.01)
        self.follower = TrajectoryFollower(
            description.poses['home'] if q is None else q, description.ssm.deceleration)
        self.t = 0
        self.body = far_body() if body is None else body
        self.sent = []

    def task(self, tp=0, tc=0, tx=0, ty=0, hp=0, hc=0, bp=0, bc=0):
        self.bridge.task_state(dict(tp=tp, tc=tc, tx=tx, ty=ty, hp=hp, hc=hc, bp=bp, bc=bc),
                               self.t)

    def run(self, seconds, body=None):
        commands = []
        for _ in range(int(round(seconds / 0.01))):
            self.bridge.skeleton(jitter(self.body if body is None else body), self.t, self.t)
            self.bridge.joint_state(JOINT_NAMES, self.follower.q, self.follower.qd, self.t,
                                    self.t)
            command = self.bridge.tick(self.t)
            if command.trajectory is not None:
                self.follower.follow(command.trajectory)
                self.sent.append(command.trajectory)
            self.follower.step(0.01, command.override)
            commands.append(command)
            self.t += 10 * MS
        return commands


def test_joint_states_are_checked_reordered_and_extra_joints_ignored(setup):
    rig = Rig(setup)
    bridge = rig.bridge
    q = rig.description.poses['home']
    names = list(reversed(JOINT_NAMES)) + ['gripper_joint']
    bridge.joint_state(names, list(q[::-1]) + [0.5], [0.0] * 7, 0, 0)
    np.testing.assert_array_equal(bridge.q, q)
    for positions, message in (
            (list(q[:5]) + [math.nan], 'wrist_3_joint is nan'),
            (list(q[:2]) + [3.5] + list(q[3:]), 'elbow_joint = 3.5000 rad is outside')):
        with pytest.raises(InputError, match=message):
            bridge.joint_state(JOINT_NAMES, positions, [0.0] * 6, 1, 1)
    with pytest.raises(InputError, match='without wrist_3_joint'):
        bridge.joint_state(JOINT_NAMES[:5], q[:5], [0.0] * 5, 1, 1)
    np.testing.assert_array_equal(bridge.q, q)       # nothing kept from a refused state
    # a sample from a clock ahead would look fresh after its source stopped: refused
    with pytest.raises(InputError, match='joint state stamped 0.060 s ahead'):
        bridge.joint_state(JOINT_NAMES, q, [0.0] * 6, 61 * MS, 1 * MS)
    # a clock ahead by more than clock_skew (5 ms) is refused: every ms of it would be 2 mm
    # of the person's unseen travel left out of S_p (an adversarial review's finding)
    with pytest.raises(InputError, match='0.006 s ahead'):
        bridge.joint_state(JOINT_NAMES, q, [0.0] * 6, 7 * MS, 1 * MS)
    bridge.joint_state(JOINT_NAMES, q, [0.0] * 6, 5 * MS, 1 * MS)     # within clock_skew
    body = body_capsules(np.array([[2.0, 0.0, 1.0]]))
    with pytest.raises(InputError, match='skeleton stamped 1.000 s ahead'):
        bridge.skeleton(body, 1000 * MS, 0)
    assert bridge.body is None
    with pytest.raises(InputError, match='unknown action'):
        bridge.action('fly', 0)


def test_no_data_is_a_protective_stop_with_its_reason(setup):
    description, programs, arm = setup
    bridge = Bridge(description, programs, arm, period=0.01)
    command = bridge.tick(0)
    assert command.stop and command.override == 0.0 and command.reason == 'no joint state yet'
    q = description.poses['home']
    bridge.joint_state(JOINT_NAMES, q, np.zeros(6), 0, 0)
    command = bridge.tick(0)
    assert command.stop and 'no human data' in command.reason
    assert command.reports and command.reports[0].message.startswith('protective stop')
    bridge.joint_state(JOINT_NAMES, q, np.zeros(6), 0, 200 * MS)
    assert 'joint state 0.200 s old' in bridge.tick(200 * MS).reason


def test_ct_runs_the_program_and_its_cycles_count_by_waypoints(setup):
    rig = Rig(setup)
    rig.run(0.3)                                   # SSM clears (resume_time)
    rig.task(tp=1, tc=2, tx=0)
    rig.bridge.action('ct', rig.t)
    commands = rig.run(0.02)
    program = rig.sent[-1]
    assert program.kind == 'program' and program.marks == (-1, 0, 1, 2, 3)
    assert rig.bridge.progress.cycles == 2 and rig.bridge.progress.cycles_done == 0
    rig.task(tp=1, tc=2, tx=0, ty=2, bp=1, bc=2)
    rig.bridge.action('nw', rig.t)
    commands = rig.run(program.duration + 0.5)
    assert rig.bridge.progress.cycles_done == 2 and rig.bridge.progress.complete
    assert max(c.override for c in commands) == 1.0       # far from the person: full speed
    assert len(rig.sent) == 1                               # nw continued, no new goal


def test_ineffective_ct_and_requests_leave_the_motion_as_it_is(setup):
    rig = Rig(setup)
    rig.run(0.3)
    rig.task(tp=1, tc=1, tx=1)                     # a human-only task: ct cannot commit
    rig.bridge.action('ct', rig.t)
    rig.run(0.1)
    assert rig.sent == [] and rig.bridge.progress is None
    rig.task(tp=1, tc=1, tx=0)
    rig.bridge.action(CT, rig.t)
    rig.run(0.3)
    before = len(rig.sent)
    for request in (RH1, RH2, MH):
        rig.bridge.action(request, rig.t)
        commands = rig.run(0.05)
        assert len(rig.sent) == before and all(c.motion == 'program' for c in commands)
    rig.bridge.action(DN, rig.t)
    commands = rig.run(0.05)
    assert all(c.override == 0.0 and c.motion == 'hold' for c in commands)
    rig.bridge.action(MH, rig.t)                   # a hold stays a hold
    assert rig.run(0.02)[-1].override == 0.0 and len(rig.sent) == before


def test_a_new_motion_waits_for_a_safe_point_and_the_program_resumes_after_a_retreat(setup):
    rig = Rig(setup)
    rig.run(0.3)
    rig.task(tp=1, tc=2, tx=2)
    rig.bridge.action('ct', rig.t)
    rig.task(tp=1, tc=2, tx=2, ty=2, bp=1, bc=2)
    rig.run(0.45)                                  # mid-way to the side station, at speed
    assert np.max(np.abs(rig.follower.qd)) > 0.5
    rig.bridge.action(DP, rig.t)
    commands = rig.run(1.5)
    braking = [c for c in commands if c.motion == 'braking']
    assert braking and all(c.override == 0.0 and c.trajectory is None for c in braking)
    retreat = [i for i, c in enumerate(commands) if c.trajectory is not None]
    assert len(retreat) == 1 and commands[retreat[0]].trajectory.kind == 'retreat'
    assert retreat[0] == len(braking)              # the goal came when braking ended, not before
    start = commands[retreat[0]].trajectory.positions[0]
    assert not np.allclose(start, rig.description.poses['home'], atol=0.05)   # mid-path stop
    rig.run(2.0)
    np.testing.assert_allclose(rig.follower.q, rig.description.poses['retreat'], atol=1e-9)
    done = rig.bridge.progress.cycles_done
    run = rig.bridge.run
    expected = run.segments_done if run.started else -1    # the segment it was on
    rig.bridge.action(NW, rig.t)                   # nw: back to the program where it stopped
    rig.run(0.05)
    rejoin = rig.sent[-1]
    assert rejoin.kind == 'program' and rejoin.marks[0] == expected
    assert rejoin.marks[1:] == tuple(range(max(expected, -1) + 1, 4))
    rig.run(rejoin.duration + 0.5)
    assert rig.bridge.progress.cycles_done == 2 > done


def test_dm_is_capped_at_the_collaboration_speed(setup):
    rig = Rig(setup)
    rig.run(0.3)
    rig.bridge.action(DM, rig.t)
    commands = rig.run(3.0)
    moving = [c for c in commands if c.motion == 'collaboration']
    assert moving and max(c.override for c in moving) == pytest.approx(0.3)


@pytest.mark.parametrize('action', [NW, MH, RH1, RH2])
def test_an_accepted_joint_request_starts_the_shared_program_on_nw_and_on_mh(setup, action):
    """The model's robot works under every action its configuration does not pause (nw, mh,
    the requests: MODEL.md 3.2), so the committed robot's program runs under each (issue 34:
    under mh it stayed unstarted, and qmdp, which motivates, left the arm idle 77% of the
    time); after dn a request or mh leaves the hold."""
    rig = Rig(setup)
    rig.run(0.3)
    rig.bridge.action(NW, rig.t)                   # the bridge starts held: leave the hold
    rig.task(tp=1, tc=1, tx=3, ty=3, hp=1, hc=1, bp=1, bc=1)
    rig.bridge.action(action, rig.t)
    rig.run(0.02)
    assert rig.sent[-1].kind == 'program' and rig.bridge.progress.nature == 3
    rig.task()                                     # the task ended: the share is dropped
    assert rig.bridge.progress is None
    held = Rig(setup)
    held.run(0.3)
    held.bridge.action(DN, held.t)
    held.task(tp=1, tc=1, tx=3, ty=3, hp=1, hc=1, bp=1, bc=1)
    held.bridge.action(action, held.t)
    commands = held.run(0.05)
    if action == NW:
        assert held.sent[-1].kind == 'program'
    else:
        assert held.sent == [] and all(c.override == 0.0 for c in commands)


def test_ssm_caps_every_action_and_a_close_person_stops_the_arm(setup):
    description = setup[0]
    near = far_body(1.35)                          # at the table, hands on it
    for action in (NW, CT, DP, DM):
        rig = Rig(setup)
        rig.run(0.3)
        rig.task(tp=1, tc=2, tx=3, ty=0)
        rig.bridge.action(action, rig.t)
        rig.task(tp=1, tc=2, tx=3, ty=2 if action == CT else 0, bp=1, bc=2)
        commands = rig.run(2.0, body=near)
        for c in commands:
            if c.ssm is not None and c.trajectory is None and rig.bridge.active is not None:
                assert c.override <= c.ssm.override + 1e-12
        # The arm's speed bound stays within SSM's allowed speed at every tick.
        for c in commands:
            if c.ssm is not None and c.ssm.allowed_speed is not None and not c.stop:
                assert c.override * (rig.bridge.active.nominal_speed if rig.bridge.active
                                     else 0.0) <= c.ssm.allowed_speed + 1e-9
    from hrc_ros.core.cell.person import STATION_ANGLE, SimulatedPerson
    from hrc_ros.core.cell.tracking import K4ABT_JOINTS
    person = SimulatedPerson(1, seed=0)
    person.theta, person.rho, person.reach = STATION_ANGLE, 1.1, 1.0   # reaching in
    touching = body_capsules(person.keypoints(), K4ABT_JOINTS)
    rig = Rig(setup)
    rig.run(0.3)
    rig.bridge.action(DM, rig.t)
    commands = rig.run(4.0, body=touching)
    assert any(c.stop and 'below the protective distance' in c.reason for c in commands)
    assert description.ssm.min_speed > 0


# -- the cell with the arm ----------------------------------------------------------------------
def test_robot_runs_decides_whether_the_robots_counter_falls():
    task = {n: np.array([v]) for n, v in zip(TASK_VARIABLES, (1, 2, 0, 2, 0, 0, 1, 2))}
    assert step_task(task, NW, False)['bc'][0] == 1                  # the model's rule
    assert step_task(task, NW, False, robot_runs=False)['bc'][0] == 2
    assert step_task(task, DN, False)['bc'][0] == 2
    assert step_task(task, DN, False, robot_runs=True)['bc'][0] == 1
    last = {**task, 'bc': np.array([1]), 'tc': np.array([1])}
    assert step_task(last, NW, False, robot_runs=False)['tp'][0] == 1   # not complete yet
    assert step_task(last, NW, False, robot_runs=True)['tp'][0] == 0


def test_level_of_distance_bands():
    from hrc_ros.core.decision.observation import level_of_distance
    assert [level_of_distance(s) for s in (-0.1, 0.0, 0.19, 0.2, 0.59, 0.6, 1.19, 1.2, 5)] == \
        [0, 0, 0, 1, 1, 2, 2, 3, 3]
    with pytest.raises(ValueError):
        level_of_distance(math.nan)


def test_ssm_only_works_and_hands_the_persons_tasks_by_the_work_plan():
    from hrc_ros.core.robot.cell import ssm_only_action
    def task(tp, tx, ty):
        return dict(tp=tp, tx=tx, ty=ty)
    assert ssm_only_action(task(1, 0, 0)) == CT and ssm_only_action(task(2, 2, 0)) == CT
    assert ssm_only_action(task(1, 1, 0)) == RH1 and ssm_only_action(task(1, 3, 0)) == RH2
    assert ssm_only_action(task(1, 0, 2)) == NW and ssm_only_action(task(0, 0, 0)) == NW


def test_the_integrators_rule_hands_either_agent_tasks_to_the_person():
    """The second baseline (docs/ROBOT.md 4): ssm_only's work plan, except that a task either
    agent can do goes to the person; outside the decision layer, selectable in the batch."""
    from hrc_ros.core.robot.cell import (BASELINES, CELL_SELECTORS, integrator_action,
                                         ssm_only_action)
    from hrc_ros.core.decision.selection import SELECTORS
    assert integrator_action(dict(tp=2, tx=2, ty=0)) == RH1
    for tp, tx, ty in ((1, 0, 0), (1, 1, 0), (1, 3, 0), (1, 2, 2), (1, 2, 1), (0, 0, 0)):
        task = dict(tp=tp, tx=tx, ty=ty)
        assert integrator_action(task) == ssm_only_action(task)
    assert 'integrator' in CELL_SELECTORS and 'integrator' in BASELINES
    assert 'integrator' not in SELECTORS


@pytest.fixture(scope='module')
def cell(model, policy):
    from hrc_ros.core.robot.cell import ArmCell
    return ArmCell(model, policy)


def test_a_robot_task_takes_the_models_epochs_at_full_speed_and_more_when_slowed(cell):
    from hrc_ros.core.robot.cell import person_seed
    from hrc_ros.core.study.simulation import Scenario
    # A task of 2 epochs for either agent (its station next to home), the person outside the
    # middle circle (d = 3) and calm.
    scenario = Scenario((0, 0, 1, 2, 2, 0, 0, 0, 0, 0, 3), (), 6)
    fast = cell.episode(scenario, [7, 0], person_seed(0, 0), 'ssm_only', record=True)
    assert fast.actions[:3] == ['ct', 'nw', 'nw'] and fast.tasks_completed == 1
    # The model: ct at epoch 1 (bc = 2), nw at 2 (bc 1), nw at 3 (bc 0, complete).
    assert [x[TASK_VARIABLES.index('bc')] for x in fast.task_states[:4]] == [0, 2, 1, 0]
    # The same task with the person at the shared table (d = 1, hands on it): SSM slows the
    # arm, the counter waits for the cycles, the task takes longer than the model says.
    near = Scenario((0, 0, 1, 2, 2, 0, 0, 0, 0, 0, 1), (), 12)
    slow = cell.episode(near, [7, 0], person_seed(0, 0), 'ssm_only', record=True)
    bc = [x[TASK_VARIABLES.index('bc')] for x in slow.task_states]
    assert bc[:3] == [0, 2, 2] and slow.stop_time + slow.idle_time > fast.stop_time


def test_a_batch_episode_can_follow_given_actions_and_refuses_a_wrong_list(cell):
    """`actions=`: the robot's actions of a recorded run instead of the selector's, epoch by
    epoch (the graph's, for test_robot_case_study's path check): the episode takes exactly
    those; its own actions given back reproduce it; a list of another length or with an
    unknown name is refused in one line."""
    from hrc_ros.core.robot.cell import person_seed
    from hrc_ros.core.study.simulation import Scenario
    scenario = Scenario((0, 0, 1, 2, 2, 0, 0, 0, 0, 0, 3), (), 6)
    own = cell.episode(scenario, [7, 0], person_seed(0, 0), 'ssm_only', record=True)
    assert own.actions[0] == 'ct' and own.tasks_completed == 1
    again = cell.episode(scenario, [7, 0], person_seed(0, 0), 'ssm_only', record=True,
                         actions=own.actions)
    assert again.actions == own.actions and again.task_states == own.task_states
    assert [q.tolist() for _, q in again.arm_path] == [q.tolist() for _, q in own.arm_path]
    # the robot never told to work: the task is not done and the arm never leaves home
    idle = cell.episode(scenario, [7, 0], person_seed(0, 0), 'ssm_only', record=True,
                        actions=['nw'] * 6)
    assert idle.actions == ['nw'] * 6 and idle.tasks_completed == 0
    home = idle.arm_path[0][1]
    assert max(np.abs(q - home).max() for _, q in idle.arm_path) < 1e-9
    for wrong in (['nw'] * 5, ['nw'] * 5 + ['go']):
        with pytest.raises(ValueError, match='actions must name one of nw, rh1'):
            cell.episode(scenario, [7, 0], person_seed(0, 0), 'ssm_only', actions=wrong)


def test_batch_cell_keeps_ssm_and_pairs_the_episodes(model, policy):
    from hrc_ros.core.robot.cell import evaluate_arm, format_arm_paired, format_arm_table
    results = evaluate_arm(model, policy, episodes=6, epochs=25, seed=4,
                           selectors=('ssm_only', 'paper'))
    for r in results.values():
        assert np.all(r.ssm_violations == 0) and np.all(r.speed_breaches == 0)
        assert np.all(r.contacts == 0) and np.all(r.min_separation > 0)
        assert np.all(r.idle_share + r.stop_share <= 100.0 + 1e-9)
    assert results['ssm_only'].tasks_completed.sum() > 0
    again = evaluate_arm(model, policy, episodes=6, epochs=25, seed=4, selectors=('ssm_only',))
    np.testing.assert_array_equal(again['ssm_only'].tasks_per_hour,
                                  results['ssm_only'].tasks_per_hour)
    table = format_arm_table(results)
    assert 'tasks per hour' in table and table.count('±') == 12
    assert 'paper     - ssm_only  tasks per hour' in format_arm_paired(results, 'ssm_only')


def test_the_person_follows_delta_and_never_outruns_the_ssm_speed(arm):
    from hrc_ros.core.cell.person import SimulatedPerson
    person = SimulatedPerson(3, seed=5, em=2, ea=2)           # the fastest walker
    q = load_robot_description().poses['collaboration']
    from hrc_ros.core.cell.tracking import K4ABT_JOINTS
    fastest = 0.0
    seen = []
    for delta in (1, 1, 1, 0, -1, -1):
        separation = arm.distance(q, body_capsules(person.keypoints(), K4ABT_JOINTS))
        person.begin_epoch(delta, 2, 2, separation)
        for _ in range(200):
            before = person.keypoints()
            separation = arm.distance(q, body_capsules(before, K4ABT_JOINTS))
            person.step(0.01, separation)
            step = np.linalg.norm(person.keypoints() - before, axis=1).max()
            fastest = max(fastest, step / 0.01)
        seen.append(separation)
    assert fastest <= 1.6
    assert seen[0] < seen[-1] and seen[2] < seen[0]            # closer, closer, then away


def test_a_share_dropped_mid_motion_brakes_and_the_arm_stays(setup):
    # The program's goal must not resume once the bridge has nothing to do: it sends a goal
    # of no segment (stay) at the safe point, so the controller drops the old trajectory.
    rig = Rig(setup)
    rig.run(0.3)
    rig.task(tp=1, tc=2, tx=0)
    rig.bridge.action(CT, rig.t)
    rig.task(tp=1, tc=2, tx=0, ty=2, bp=1, bc=2)
    rig.run(0.5)
    assert np.max(np.abs(rig.follower.qd)) > 0.1
    rig.task()                                     # the task is gone (say, a restart)
    rig.bridge.action(NW, rig.t)
    rig.run(1.0)
    hold = rig.sent[-1]
    assert hold.kind == 'idle' and len(hold.durations) == 0
    stopped = rig.follower.q.copy()
    commands = rig.run(1.0)
    np.testing.assert_array_equal(rig.follower.q, stopped)
    assert all(c.motion == 'idle' for c in commands)


def test_a_new_goal_starts_from_rest_so_the_speed_bound_ramps_up_again():
    # After a trajectory ends at full override, the next one starts at rest: its speed
    # bound (what SSM's check takes as v_r) must start at 0, not at the old scaling times the
    # new trajectory's top speed (which broke SSM at the start of the next motion).
    description = load_robot_description()
    q0, q1 = description.poses['home'], description.poses['retreat']
    follower = TrajectoryFollower(q0, deceleration=2.0)
    follower.follow(Trajectory(JOINT_NAMES, np.array([q0, q1]), np.array([1.5]), 0.8, (-1,)))
    while not follower.done:
        follower.step(0.01, 1.0)
    follower.step(0.01, 1.0)
    follower.follow(Trajectory(JOINT_NAMES, np.array([q1, q0]), np.array([1.5]), 0.9, (-1,)))
    assert follower.speed_bound == 0.0
    assert follower.step(0.01, 1.0).speed_bound <= 2.0 * 0.01 + 1e-12


def test_hrc_evaluate_cell_arm_prints_the_table_and_writes_its_files(tmp_path, capsys):
    import csv
    import json
    from hrc_ros.core.mdp.policy import default_policy_path
    from hrc_ros.tools.evaluate import main
    if not default_policy_path().is_file():
        pytest.skip('no shipped policy')
    assert main(['--cell', 'arm', '--episodes', '3', '--epochs', '6', '--out',
                 str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert '3 episodes x 6 epochs of 1 s' in out and 'real time on one core' in out
    table = out.split('paired differences')[0]
    rows = [line.split()[0] for line in table.splitlines() if '±' in line]
    # the baseline first, the cell's default decision (paper) next, the integrator's rule too
    assert rows == ['ssm_only', 'paper', 'qmdp', 'integrator']
    assert 'paired differences to ssm_only' in out
    summary = json.loads((tmp_path / 'summary.json').read_text())
    assert summary['baseline'] == 'ssm_only' and summary['settings']['cell'] == 'arm'
    # no --config: the arm's model and its shipped policy (docs/ROBOT.md 4)
    assert Path(summary['settings']['config']).name == 'arm.yaml'
    assert Path(summary['settings']['policy']).name == 'arm.npz'
    assert all(v['ssm_violations']['mean'] == 0 for v in summary['selectors'].values())
    with (tmp_path / 'episodes.csv').open() as f:
        assert len(list(csv.DictReader(f))) == 12
    for argv, message in ((['--true-config', 'x.yaml'], '--true-config is for'),
                          (['--selectors', 'ssm_only,best'], "unknown selector 'best'"),
                          (['--scenario', 'case-study'], 'random task streams'),
                          (['--baseline', 'mdp'], "--baseline 'mdp' must be one of")):
        with pytest.raises(SystemExit):
            main(['--cell', 'arm', '--out', str(tmp_path)] + argv)
        assert message in capsys.readouterr().err


def test_a_second_writer_can_only_slow_the_arm(setup):
    """Skeletons of another writer (publication sequence numbers off the followed line) count
    beside the followed one's, for human_timeout: SSM takes the nearest body. Joint states of
    another writer are refused and hold the arm for SECOND_WRITER_HOLD."""
    description, programs, arm = setup
    bridge = Bridge(description, programs, arm, period=0.01)
    q = description.poses['home']
    near = body_capsules(np.array([[0.4, -0.3, 0.8]]))       # S about 0.3 m: no speed is safe
    t = 0
    for seq in range(1, 41):                   # 0.4 s of one writer far away: free
        bridge.joint_state(JOINT_NAMES, q, np.zeros(6), t, t, sequence=seq)
        bridge.skeleton(far_body(), t, t, sequence=seq)
        command = bridge.tick(t)
        t += 10 * MS
    assert not command.stop
    # a second writer (its numbers restart) reports the person near: it is taken, and a far
    # skeleton of the first writer stamped later does not free the arm from it
    bridge.skeleton(near, t, t, sequence=1)
    bridge.skeleton(far_body(), t + 4 * MS, t, sequence=41)
    command = bridge.tick(t)
    assert command.stop and 'below the protective distance' in command.reason
    assert command.separation.distance < 0.5
    # the followed writer's skeleton stamped before the newest held counts too (not dropped)
    bridge2 = Bridge(description, programs, arm, period=0.01)
    bridge2.joint_state(JOINT_NAMES, q, np.zeros(6), t, t)
    bridge2.skeleton(far_body(), t, t)
    bridge2.skeleton(near, t - 20 * MS, t)
    assert bridge2.tick(t).stop
    # the near body ages out after human_timeout: the far followed writer alone frees the arm
    for seq in range(42, 122):
        t += 10 * MS
        bridge.joint_state(JOINT_NAMES, q, np.zeros(6), t, t, sequence=seq)
        bridge.skeleton(far_body(), t, t, sequence=seq)
        command = bridge.tick(t)
    assert not command.stop and command.separation.distance > 2
    # joint states of another writer: refused, and the arm holds while it writes
    with pytest.raises(InputError, match='joint_states of a second writer'):
        bridge.joint_state(JOINT_NAMES, description.poses['retreat'], np.zeros(6), t, t,
                           sequence=5)
    command = bridge.tick(t)
    assert command.stop and command.override == 0.0
    assert 'second writer of joint_states' in command.reason
    np.testing.assert_array_equal(bridge.q, q)
    t += int(1.05e9)                           # silent for SECOND_WRITER_HOLD (1 s): free again
    bridge.joint_state(JOINT_NAMES, q, np.zeros(6), t, t, sequence=122)
    bridge.skeleton(far_body(), t, t, sequence=122)
    assert 'second writer' not in bridge.tick(t).reason
