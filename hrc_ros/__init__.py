"""hrc_ros: stochastic decision making for human-robot collaboration on ROS 2 Jazzy.

`hrc_ros.core` implements the POMDP of docs/MODEL.md and the decision science without ROS;
`hrc_ros.tools` holds the ROS-free commands; `hrc_ros.ros` runs the core on the ROS 2 graph
(the nodes, conversions, bags, the case study). See README.md and docs/DESIGN.md.
"""

__version__ = '0.2.0'
