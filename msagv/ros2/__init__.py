"""The controller and the plant as ROS 2 nodes (rclpy): ``msagv ros2 controller`` and
``msagv ros2 plant`` (docs/ROS2.md).

The messages, frames, joint names and their CDR encoding are :mod:`msagv.bridge.ros_msgs`'
(the same as the ROS 2 channels of every recording); this package only moves them with
rclpy, on whichever RMW the user runs. It imports rclpy lazily (:mod:`.runtime`), so the
rest of the project works without ROS 2 installed.
"""
