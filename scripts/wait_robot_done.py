"""Wait until every named robot's /NAME/status says it arrived or failed; exit 0 if all arrived, else 1.

``run_scenario.sh --stay`` runs the robots without ``~once``, so that they and their
callback services stay up after the run; this watcher ends the script's wait. It
prints one line per robot that did not arrive, ``NAME STATE: REASON``.

    wait_robot_done.py NAME...
"""

import sys
import threading

import rospy

from drvs.msg import RobotStatus


def main(names: list[str]) -> int:
    done: dict[str, RobotStatus] = {}
    lock = threading.Lock()  # guards done
    all_done = threading.Event()

    def on_status(msg: RobotStatus, name: str) -> None:
        if msg.state in (RobotStatus.ARRIVED, RobotStatus.FAILED):
            with lock:
                done.setdefault(name, msg)
                if len(done) == len(names):
                    all_done.set()

    rospy.init_node('run_scenario_robot_done', anonymous=True)
    for name in names:
        rospy.Subscriber(f'/{name}/status', RobotStatus, on_status, callback_args=name, queue_size=5)
    while not all_done.wait(0.5):
        if rospy.is_shutdown():
            return 130
    failed = [(name, done[name]) for name in names if done[name].state != RobotStatus.ARRIVED]
    for name, msg in failed:
        print(f'{name} {msg.state_name}: {msg.reason}')
    return 1 if failed else 0


if __name__ == '__main__':
    if len(sys.argv) < 2:
        sys.exit(f'usage: {sys.argv[0]} NAME...  (the robots to wait for)')
    sys.exit(main(rospy.myargv()[1:]))
