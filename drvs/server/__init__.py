"""The DRVS server's decisions: the registry and its spatial index, dispatch, rate limits, the watch
table, callback checks and log throttling. No rospy; see docs/architecture.md."""
