"""Glue between the project's plain modules and rclpy: params dataclasses as declared ROS
parameters, QoS profiles, the node runner and the ``t42 up`` supervisor.  The graph itself
is rclpy's; nothing here imitates it."""
