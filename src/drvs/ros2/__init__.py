"""drvs-ros2 (the `ros2` extra): DRVS's fused tracks on a robot's own ROS 2 topics, over Cyclone DDS
(drvs.ros2.bridge, drvs.ros2.cli), and DRVS recordings as rosbag2 (drvs.ros2.bag). No ROS
installation is needed: the message types come from the upstream .msg files shipped in
drvs/ros2/msg (drvs.ros2.types). docs/ros2.md describes the topics and how Nav2 and RViz use them."""
