"""The ROS 2 bridge (``cochlea-ros2``, optional extra ``ros``): a run's joint states, frames
and robot description on ROS 2 topics, published by a process of its own from the run's log
files, never from the 1 kHz loop (docs/logs.md, "Live on ROS 2")."""
