"""Small ROS-free pieces that every layer of the package shares.

* :mod:`asgp_ros.common.topics` -- the ROS topic names, defined once;
* :mod:`asgp_ros.common.paramspec` -- the parameter tables of the nodes (name, default,
  description, range) and their checks; the rclpy side is :mod:`asgp_ros.nodes.parameters`;
* :mod:`asgp_ros.common.fileio` -- files a user keeps: atomic output, output paths checked
  before work starts, temporaries removed on signals as on exceptions.

They import nothing else of ``asgp_ros`` (and no rclpy), so the core, the simulators, the
nodes, the learning side and the command line can all use them without coming to depend on
one another through them. Nothing is imported here: a module costs only what it imports.
"""
