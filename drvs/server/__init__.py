"""The DRVS server's decisions: the registry and its spatial index, who may register, dispatch, rate
limits, the watch table, request and callback checks, its answers and its settings. No rospy; see
docs/architecture.md."""
