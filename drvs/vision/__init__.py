"""A vision system's decisions: frames, camera models, calibration, the processing pipeline, its
registration with the server and its watches. No rospy, no pybullet; see docs/architecture.md."""
