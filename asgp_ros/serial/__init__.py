"""ROS-free link to the joystick interface board: protocol codec and link manager."""
