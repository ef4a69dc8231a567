"""The blind robot's decisions: perception from DRVS answers, the occupancy map, D* Lite, the
controller, when to ask (polling and watch schedules) and its status. No rospy; see docs/architecture.md."""
