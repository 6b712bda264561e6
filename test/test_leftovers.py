"""conftest's check that no module leaves a node process running in the run's DDS domain
(test/leftovers.py): found by its domain and command, given a grace to finish, then killed."""

import os
import random
import subprocess
import sys
import time
import uuid

from leftovers import RUN_VARIABLE, ancestors, graph_processes, is_ours, left_behind

# no real run's domain (1..232), and a run name of these tests' own: a second suite running
# these tests on the same host never sees this one's processes
DOMAIN = 100_000 + random.SystemRandom().randrange(10 ** 6)
RUN = uuid.uuid4().hex


def sleeper(domain: int, *words: str, seconds: float = 60.0, run: str = RUN,
            worker: str = 'gw0') -> subprocess.Popen:
    env = {**os.environ, 'ROS_DOMAIN_ID': str(domain), RUN_VARIABLE: run,
           'PYTEST_XDIST_WORKER': worker}
    return subprocess.Popen([sys.executable, '-c', f'import time; time.sleep({seconds})',
                             *words], env=env)


def test_a_command_of_ours_is_told_from_a_path_that_names_the_package():
    assert is_ours(['/x/.venv/bin/python', '/x/.venv/bin/decision_node', '--ros-args'])
    assert is_ours(['python', '-m', 'hrc_ros.ros.entry', 'cobot_sim_node'])
    assert is_ours(['/usr/bin/hrc-case-study', '--robot', 'sim'])
    assert not is_ours(['python', '-m', 'pytest', '/home/me/hrc_ros/test'])
    assert not is_ours(['/home/me/hrc_ros/.venv/bin/python', '-m', 'hrc_rosx'])


def test_a_node_left_in_the_domain_is_found_killed_and_named():
    left = sleeper(DOMAIN, 'robot_bridge_node')
    other_domain = sleeper(DOMAIN + 1, 'robot_bridge_node')
    not_ours = sleeper(DOMAIN, 'chromium')
    quick = sleeper(DOMAIN, 'decision_node', seconds=1.0)       # its stop ends within the grace
    other_run = sleeper(DOMAIN, 'robot_bridge_node', run=uuid.uuid4().hex)   # the same domain
    other_worker = sleeper(DOMAIN, 'hrc-bag', worker='gw1')    # its own pick of this domain
    try:
        deadline = time.monotonic() + 10.0
        while len(graph_processes(DOMAIN, set())) < 4 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert {pid for pid, _ in graph_processes(DOMAIN, set())} == \
            {left.pid, quick.pid, other_run.pid, other_worker.pid}
        assert {pid for pid, _ in graph_processes(DOMAIN, set(), RUN, 'gw0')} == \
            {left.pid, quick.pid}
        assert {pid for pid, _ in graph_processes(DOMAIN, set(), RUN)} == \
            {left.pid, quick.pid, other_worker.pid}
        assert graph_processes(DOMAIN, {left.pid, quick.pid}, RUN, 'gw0') == []
        # a process whose stop ends within the grace is not left behind (nor killed)
        assert left_behind(DOMAIN, 60.0, {left.pid}, RUN, 'gw0') == []
        assert quick.wait(5.0) == 0
        found = left_behind(DOMAIN, 0.5, ancestors(os.getpid()), RUN, 'gw0')
        assert [pid for pid, _ in found] == [left.pid]
        assert 'robot_bridge_node' in found[0][1]
        assert left.wait(5.0) == -9                 # killed
        assert other_domain.poll() is None and not_ours.poll() is None
        assert other_run.poll() is None             # another run's, in the same domain: not ours
        assert other_worker.poll() is None          # another worker's: not ours
    finally:
        for p in (left, other_domain, not_ours, quick, other_run, other_worker):
            p.kill()
            p.wait()


def test_nothing_left_is_nothing_found_at_once():
    started = time.monotonic()
    assert left_behind(DOMAIN + 2, 5.0, set()) == []
    assert time.monotonic() - started < 2.0


def test_ancestors_hold_this_process_and_its_parent():
    assert {os.getpid(), os.getppid()} <= ancestors(os.getpid())
