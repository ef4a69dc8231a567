"""ROS glue: message conversions, parameters and the node classes."""
