"""Command-line tools: drvs_ask, drvs_calibrate, drvs_check_world, drvs_report (see docs/)."""
