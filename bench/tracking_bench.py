"""What one body-tracking frame costs body_tracking_node, step by step, for 1 and 2 bodies.

    .venv/bin/python bench/tracking_bench.py            # ~10 s
    .venv/bin/python bench/tracking_bench.py --frames 2000

Per frame, as the node does it: rclpy deserializes the driver's MarkerArray (32 SPHERE markers
a body), `conversions.body_frame_from_msg` validates it into a BodyFrame, `BodyTracking.frame`
transforms, selects and derives, and the skeleton and joint state are built and serialized.
The Azure Kinect tracks at 30 Hz, so the sum times 30 is the share of one core the adapter takes.
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time

import numpy as np
from rclpy.serialization import deserialize_message, serialize_message
from visualization_msgs.msg import MarkerArray

from hrc_ros.core.decision.observation import HUMAN_JOINTS
from hrc_ros.core.cell.tracking import BodyTracking, SyntheticBody
from hrc_ros.ros import conversions as conv

TRACKER_HZ = 30.0


def frames(bodies: int, count: int):
    """`count` serialized driver frames of `bodies` synthetic bodies walking about."""
    rng = np.random.default_rng(0)
    people = [SyntheticBody(direction=(np.cos(a), np.sin(a), 0.0))
              for a in np.linspace(0, np.pi, bodies, endpoint=False)]
    out = []
    for k in range(count):
        stamp = 100.0 + k / TRACKER_HZ
        joints = {b + 1: p.step(rng.uniform(0, 1.5, 6), 1 + b, stamp)
                  for b, p in enumerate(people)}
        out.append(serialize_message(conv.body_frame_to_msg(
            joints, conv.seconds_to_stamp(stamp), 'depth_camera_link')))
    return out


def measure(data: list[bytes]) -> dict:
    tracking = BodyTracking()
    timings = {'deserialize': [], 'validate': [], 'track': [], 'publish': []}
    for raw in data:
        t0 = time.perf_counter()
        msg = deserialize_message(raw, MarkerArray)
        t1 = time.perf_counter()
        frame = conv.body_frame_from_msg(msg, 'depth_camera_link')
        t2 = time.perf_counter()
        step = tracking.frame(frame)
        t3 = time.perf_counter()
        stamp = msg.markers[0].header.stamp
        serialize_message(conv.keypoints_to_msg(step.keypoints, stamp))
        if step.velocities is not None:
            serialize_message(conv.joint_state_to_msg(HUMAN_JOINTS, step.velocities,
                                                      step.angles, stamp))
        t4 = time.perf_counter()
        for name, dt in zip(timings, (t1 - t0, t2 - t1, t3 - t2, t4 - t3)):
            timings[name].append(dt * 1e3)
    return {name: float(np.median(v)) for name, v in timings.items()}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=' '.join(__doc__.split('\n\n')[0].split()))
    parser.add_argument('--frames', type=int, default=600)
    args = parser.parse_args(argv)
    print(f'body_tracking_node per frame, median of {args.frames} frames (ms):')
    for bodies in (1, 2):
        cost = measure(frames(bodies, args.frames))
        total = sum(cost.values())
        print(f'  {bodies} bod{"y" if bodies == 1 else "ies"} ({32 * bodies} markers): '
              + ', '.join(f'{name} {ms:.2f}' for name, ms in cost.items())
              + f'; total {total:.2f} ms = {100 * total * TRACKER_HZ / 1e3:.0f}% of a core at '
              f'{TRACKER_HZ:.0f} Hz')
    command = ' '.join(shlex.quote(a) for a in [sys.executable, 'bench/tracking_bench.py',
                                                *(argv if argv is not None else sys.argv[1:])])
    print(f'reproduce: {command}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
