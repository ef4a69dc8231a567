"""DRVS, the Distributed Robotic Vision Service.

The core library (this package's modules) does not import rospy; the ROS glue
lives in :mod:`drvs.ros`, and the generated message and service types in
:mod:`drvs.msg` and :mod:`drvs.srv`.
"""
