"""drvs_site_link between two private masters: topics of master A arrive on master B with their
types (a latched one latched), again after their publisher was killed and started again, and the
link never registers with master A. Bad parameters: one message, exit 2."""

import json
import os
import signal
import sys

import pytest

from drvs.testing import RosHarness, wait_for

TALKER = """
import sys, rospy
from std_msgs.msg import String
rospy.init_node('talker')
latched = rospy.Publisher('/latched', String, queue_size=1, latch=True)
latched.publish(String('latched ' + sys.argv[1]))
chatter = rospy.Publisher('/chatter', String, queue_size=1)
rospy.Timer(rospy.Duration(0.05), lambda _: chatter.publish(String(sys.argv[1])))
rospy.spin()
"""
LISTENER = """
import json, rospy
from std_msgs.msg import String
rospy.init_node('listener')
def heard(message, topic):
    print(json.dumps([topic, message.data]), flush=True)
for topic in ('/chatter', '/latched'):
    rospy.Subscriber(topic, String, heard, callback_args=topic)
rospy.spin()
"""


def heard(listener) -> list[list[str]]:
    """What the listener received so far: [topic, data] per message."""
    return [json.loads(line) for line in listener.log(tail=100000).splitlines() if line.startswith('[')]


@pytest.fixture
def site_b():
    with RosHarness() as harness:
        yield harness


def test_topics_of_one_master_arrive_on_the_other_also_after_their_publisher_restarted(ros, site_b):
    talker = ros.spawn('talker', [sys.executable, '-c', TALKER, 'first'])
    link = site_b.start_node(
        'nodes/drvs_site_link',
        'site_link',
        params={'master': ros.master.uri, 'topics': ['/chatter', '/latched'], 'poll_period': 0.2},
    )
    listener = site_b.spawn('listener', [sys.executable, '-c', LISTENER])

    def got(message):
        assert link.running(), site_b.describe()
        return message in heard(listener)

    wait_for(lambda: got(['/chatter', 'first']), 20, 'first on master B', on_timeout=site_b.describe)
    wait_for(
        lambda: got(['/latched', 'latched first']), 10, 'the latched message', on_timeout=site_b.describe
    )
    types = dict(site_b.master.call('getTopicTypes'))
    assert types['/chatter'] == types['/latched'] == 'std_msgs/String'
    # It subscribes over TCPROS without registering with master A.
    _, subscribers, _ = ros.master.system_state()
    assert '/site_link' not in {node for _, nodes in subscribers for node in nodes}
    assert '/site_link' not in ros.master.nodes()

    # Killed: the master still lists it (at an address where nobody answers) until the new one registers.
    os.kill(talker.pid, signal.SIGKILL)
    talker.process.wait(10)
    ros.spawn('talker', [sys.executable, '-c', TALKER, 'second'])
    wait_for(lambda: got(['/chatter', 'second']), 20, 'second after the restart', on_timeout=site_b.describe)
    wait_for(
        lambda: got(['/latched', 'latched second']), 10, 'the new latched one', on_timeout=site_b.describe
    )
    # A listener that comes later gets the latched message from the link.
    late = site_b.spawn('late_listener', [sys.executable, '-c', LISTENER.replace("'listener'", "'late'")])
    wait_for(lambda: ['/latched', 'latched second'] in heard(late), 10, 'latched', on_timeout=site_b.describe)


@pytest.mark.parametrize(
    'params, message',
    [
        (
            {'master': 'localhost:11311', 'topics': '/clock'},
            "~master: must be a ROS master URI http://HOST:PORT/, got 'localhost:11311'",
        ),
        (
            {'master': 'http://127.0.0.1:1/', 'topics': 'clock'},
            '~topics: must be one or more global topic names (/name/name), comma-separated or a list, '
            "got 'clock'",
        ),
    ],
)
def test_bad_parameters_are_one_message_and_exit_2(ros, params, message):
    node = ros.start_node('nodes/drvs_site_link', 'site_link', params=params)
    wait_for(lambda: not node.running(), 20, 'the link to exit', on_timeout=ros.describe)
    assert node.process.returncode == 2, node.describe()
    assert message in node.log(), node.describe()
