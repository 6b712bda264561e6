"""The cell around the decision layer, without ROS: the simulated human (`human`), injected
faults (`faults`), body-tracking input (`tracking`) and the cell drawn as markers (`view`)."""
