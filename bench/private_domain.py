"""A bench run's private DDS domain: set before rclpy is imported (the benches that start nodes).

HRC_BENCH_DOMAIN_ID, else a random domain in 100..199; discovery on this host only, with the
fast discovery profile of config/ unless one is set.
"""

import os
import random
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def use_private_domain() -> None:
    os.environ['ROS_DOMAIN_ID'] = os.environ.get('HRC_BENCH_DOMAIN_ID',
                                                 str(random.SystemRandom().randint(100, 199)))
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    os.environ.setdefault('FASTRTPS_DEFAULT_PROFILES_FILE',
                          str(ROOT / 'config' / 'fastdds_fast_discovery.xml'))
