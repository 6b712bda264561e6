"""ament_python package hrc_ros: colcon build (ROS 2 Jazzy) and pip install alike."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'hrc_ros'

NODES = ['belief_estimator_node', 'decision_node', 'task_manager_node', 'cell_sim_node',
         'cell_view_node', 'body_tracking_node', 'tracker_sim_node', 'hmi_node',
         'robot_bridge_node', 'cobot_sim_node']
# Nodes that run only in a ROS install: they publish messages of packages with no pip wheel
# (speed_scaling_node: control_msgs/msg/SpeedScalingFactor; docs/ROBOT.md 3).
ROS_INSTALL_NODES = ['speed_scaling_node']
# The nodes, hrc-bag and hrc-case-study enter through hrc_ros.ros.entry, which installs the
# stop regime (hrc_ros/ros/stop.py) before the heavy imports: Ctrl-C during them is a clean stop.
TOOLS = {
    'hrc-solve': 'hrc_ros.tools.solve:main',
    'hrc-simulate': 'hrc_ros.tools.simulate:main',
    'hrc-evaluate': 'hrc_ros.tools.evaluate:main',
    'hrc-fit': 'hrc_ros.tools.fit:main',
    'hrc-bag': 'hrc_ros.ros.entry:hrc_bag',
    'hrc-case-study': 'hrc_ros.ros.entry:hrc_case_study',
    'hrc-hmi-shots': 'hrc_ros.ros.hmi.shots:main',
    'hrc-fleet': 'hrc_ros.tools.fleet:main',
}

setup(
    name=PACKAGE,
    version='0.2.0',
    packages=find_packages(exclude=['test', 'test.*', 'bench']),
    # The HMI's pages: static HTML, CSS and JavaScript, served from the package itself, with
    # the charting library the console draws its timeline with (uPlot, MIT, its licence beside).
    package_data={'hrc_ros.ros.hmi': ['static/*', 'static/vendor/*']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE]),
        ('share/' + PACKAGE, ['package.xml', 'README.md']),
        ('share/' + PACKAGE + '/config', sorted(
            glob('config/*.yaml') + glob('config/*.xml') + glob('config/*.json')
            + glob('config/*.rviz'))),
        ('share/' + PACKAGE + '/config/robot', sorted(glob('config/robot/*.yaml'))),
        ('share/' + PACKAGE + '/policies', sorted(glob('policies/*.npz'))),
        ('share/' + PACKAGE + '/policies/pomdp', sorted(glob('policies/pomdp/*.npz'))),
        ('share/' + PACKAGE + '/launch', sorted(glob('launch/*.launch.py'))),
    ],
    install_requires=['setuptools', 'numpy', 'scipy', 'pyyaml', 'mcap', 'mcap-ros2-support',
                      'matplotlib', 'pillow', 'numba', 'aiohttp>=3.14.5', 'ray>=2.58', 'grpcio',
                      'mujoco', 'playwright'],
    zip_safe=False,
    maintainer='hrc_ros maintainers',
    maintainer_email='maintainers@hrc-ros.invalid',
    description='POMDP decision making for human-robot collaboration (ROS 2 Jazzy nodes)',
    license='Apache-2.0',
    extras_require={'test': ['pytest', 'py-spy']},
    entry_points={
        'console_scripts': [f'{n} = hrc_ros.ros.entry:{n}' for n in NODES + ROS_INSTALL_NODES]
        + [f'{name} = {target}' for name, target in TOOLS.items()],
    },
)
