"""The ROS 2 bridge (issue 48): mfvs as one ROS 2 node on rmw_zenoh's wire (docs/ros2.md)."""
