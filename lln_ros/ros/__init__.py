"""ROS-side pieces shared by lln-demo and the tests: the process supervisor (start the node
executables as `ros2 run` does, on a private domain, stop them in order) and the probe node."""
