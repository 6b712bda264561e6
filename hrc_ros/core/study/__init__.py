"""The cell studied without ROS: one closed-loop trajectory (`simulation`, hrc-simulate), many
seeded, paired episodes (`evaluation`, hrc-evaluate) and their figures (`plots`)."""
