"""DRVS, the Distributed Robotic Vision Service.

Packages by role (docs/architecture.md): :mod:`drvs.server`, :mod:`drvs.vision`,
:mod:`drvs.robot` and :mod:`drvs.sim` hold the decisions, on :mod:`drvs.common` and the
plugin API :mod:`drvs.algorithms`, without rospy; :mod:`drvs.ros` is the ROS glue,
:mod:`drvs.tools` the command-line tools, :mod:`drvs.msg` and :mod:`drvs.srv` the
generated message and service types.
"""
