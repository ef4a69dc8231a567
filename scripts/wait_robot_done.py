"""Wait until /robot/status says the robot arrived (exit 0) or failed (exit 1).

``run_scenario.sh --stay`` runs the robot without ``~once``, so that it and its
callback service stay up after the run; this watcher ends the script's wait.
"""

import sys
import threading

import rospy

from drvs.msg import RobotStatus


def main() -> int:
    arrived: list[bool] = []
    done = threading.Event()

    def on_status(msg: RobotStatus) -> None:
        if msg.state in (RobotStatus.ARRIVED, RobotStatus.FAILED) and not done.is_set():
            arrived.append(msg.state == RobotStatus.ARRIVED)
            done.set()

    rospy.init_node('run_scenario_robot_done', anonymous=True)
    rospy.Subscriber('/robot/status', RobotStatus, on_status, queue_size=5)
    while not done.wait(0.5):
        if rospy.is_shutdown():
            return 130
    return 0 if arrived[0] else 1


if __name__ == '__main__':
    sys.exit(main())
