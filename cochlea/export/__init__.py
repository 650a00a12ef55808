"""Exports of a run folder to other tools' formats: ``cochlea-mcap`` writes its log as MCAP
of standard ROS 2 messages for Foxglove and ``ros2 bag`` (docs/logs.md)."""
