"""hrc_ros: stochastic decision making for human-robot collaboration on ROS 2 Jazzy.

The ROS-free core (`config`, `model`, `solver`, `policy`, `observation`, `belief`, `selection`,
`tasks`, `cell`, `simulator`, `evaluate`) implements the POMDP of shared/MODEL.md; the ROS layer
(`conversions`, `qos`, `nodes`, `bag`, `case_study`) runs it on the ROS 2 graph. See README.md
and docs/DESIGN.md.
"""

__version__ = '0.1.0'
