"""``asgp demo``: the whole smart-wheelchair system live on simulated hardware.

* :mod:`asgp_ros.demo.simhw` -- the simulated hardware without ROS: driver, joystick board
  on a pty, chair following the board's output, RGB-D renderer, look-ahead joystick plans;
* :mod:`asgp_ros.demo.hardware` -- the ROS node around it (camera, ground truth, plans);
* :mod:`asgp_ros.demo.monitor` -- live figures and the online success rate (ROS-free);
* :mod:`asgp_ros.demo.monitor_node` -- the monitoring node, which also records the bag;
* :mod:`asgp_ros.demo.processes` and :mod:`asgp_ros.demo.child` -- starting, watching and
  stopping the node processes (none outlives the demo);
* :mod:`asgp_ros.demo.report` -- the end-of-run report (figure, tables, time accounting);
* :mod:`asgp_ros.demo.orchestrator` -- the run itself.
"""
