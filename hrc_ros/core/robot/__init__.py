"""The robot side of the cell, without ROS: what turns the decision layer's actions into arm
motion, safely, and the cell measured in physical units.

- `ssm`: speed and separation monitoring (ISO/TS 15066 5.5.4): the protective separation
  distance, the largest safe speed in closed form, the override, protective stops
  (`SpeedSeparationMonitor`, sans-IO).
- `arm`: a UR5e of capsules in MuJoCo (the published DH parameters, an MJCF written here):
  forward kinematics, link speeds, the separation to a person's body capsules, cubic joint
  trajectories and a scaled trajectory controller.
- `bridge`: the robot description and motion programs (YAML), and `Bridge`, the sans-IO state
  machine from actions, task states, joint states and skeletons to trajectory goals, speed
  overrides and protective stops, with SSM below every action.
- `cell`: the cell with the arm as a seeded batch (the task book, the simulated human with a
  body, the selectors, the bridge, the arm), the ssm_only baseline, its metrics and tables
  (`hrc-evaluate --cell arm`).
- `metrics`: those figures defined once (the arm's activity per sample, tasks per hour, the
  shares, refused requests), for `cell` and the operator's console (`core.hmi.shift`).

docs/ROBOT.md describes the models, the parameters and the design of the ROS nodes around it.
"""
