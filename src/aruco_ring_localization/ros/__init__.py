"""ROS 1 adapters of aruco_ring_localization.

This subpackage is the only place that imports rospy, tf2_ros or message modules: the nodes
(one module per node, each with a ``main()`` that the thin executables in ``scripts/`` call),
message <-> numpy conversions and parameter reading. The algorithms live in the pure core one
level up and never see ROS.
"""
