"""ROS 2 adapter: PointCloud2 <-> numpy, the node, diagnostics and parameter loading (rclpy)."""
