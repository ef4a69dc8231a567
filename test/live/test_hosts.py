"""scripts/hosts.sh: separate network hosts (namespaces on a private bridge) for run_scenario --hosts.

Three hosts carry a ROS graph (master on one, publisher on another, subscriber on
the third) across the bridge; each host has its own address, no default route and
no IPv6 address; a rate limit is a tbf on both ends of the host's link; nothing of
a prefix is left after cleanup, also when the body raised or the process got
SIGINT or SIGTERM. Where namespaces cannot be made (not root, no ``ip``), the tests
that need them are skipped with that reason.
"""

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
from pathlib import Path
from urllib.parse import urlparse

import pytest

from drvs.testing import RosHarness, wait_for
from drvs.testing.harness import REPO, NodeProcess
from drvs.testing.netns import HOSTS_SH, HostsError, NetworkHosts, hosts_call, namespaces_of, unavailable

UNAVAILABLE = unavailable()
needs_namespaces = pytest.mark.skipif(UNAVAILABLE is not None, reason=f'no network hosts: {UNAVAILABLE}')


def root_links_of(prefix: str) -> list[str]:
    """The root namespace's links that name ``prefix`` (as their name, or as the namespace of their peer)."""
    listed = subprocess.run(['ip', '-o', 'link', 'show'], capture_output=True, text=True, check=True).stdout
    return [line for line in listed.splitlines() if prefix in line]


@pytest.fixture
def hosts():
    """Hosts on a fresh bridge; afterwards no namespace or root link of its prefix may remain."""
    with NetworkHosts() as made:
        yield made
    assert made.leftovers() == []
    assert root_links_of(made.prefix) == []


TALKER = """
import os, rospy
from std_msgs.msg import String
rospy.init_node('talker')
publisher = rospy.Publisher('/chatter', String, queue_size=1)
rospy.Timer(rospy.Duration(0.1), lambda _: publisher.publish(String('hello from ' + os.environ['ROS_IP'])))
rospy.spin()
"""
LISTENER = """
import json, rosgraph, rospy
from std_msgs.msg import String
rospy.init_node('listener')
message = rospy.wait_for_message('/chatter', String, timeout=30)
talker = rosgraph.Master('/listener').lookupNode('/talker')
print(json.dumps({'data': message.data, 'talker': talker, 'listener': rospy.get_node_uri()}), flush=True)
"""


@needs_namespaces
def test_ros_nodes_on_three_hosts_talk_across_the_bridge(hosts: NetworkHosts, ros: RosHarness):
    # ``ros`` after ``hosts``: its processes are stopped before the hosts are deleted.
    master, talker, listener = (hosts.add(name) for name in ('master', 'talker', 'listener'))
    # A fresh namespace has every port free: the master's address is the host's.
    uri = {'ROS_MASTER_URI': f'http://{master}:11311/'}
    ros.spawn('rosmaster', [*hosts.command('master'), 'rosmaster', '--core', '-p', '11311'], env=uri)
    ros.spawn('talker', [*hosts.command('talker'), sys.executable, '-c', TALKER], env=uri)
    node = ros.spawn('listener', [*hosts.command('listener'), sys.executable, '-c', LISTENER], env=uri)

    wait_for(lambda: not node.running(), 40, 'the listener to get a message', on_timeout=ros.describe)
    assert node.process.returncode == 0, ros.describe()
    heard = json.loads(node.log().splitlines()[-1])
    assert heard['data'] == f'hello from {talker}'
    assert urlparse(heard['talker']).hostname == talker
    assert urlparse(heard['listener']).hostname == listener


def addresses_and_routes(namespace: str) -> tuple[list[str], list[str]]:
    def lines(*argv):
        return subprocess.run(
            ['ip', '-n', namespace, *argv], capture_output=True, text=True, check=True
        ).stdout

    addresses = [' '.join(line.split()[1:4]) for line in lines('-o', 'addr', 'show').splitlines()]
    routes = [line.strip() for line in lines('route', 'show', 'table', 'main').splitlines()]
    return addresses, routes


@needs_namespaces
def test_a_host_has_its_address_and_its_subnet_only(hosts: NetworkHosts):
    first, second = hosts.add('first'), hosts.add('second')
    subnet = first.rsplit('.', 1)[0]
    assert second == f'{subnet}.2' and first == f'{subnet}.1'
    assert hosts.ip('second') == second
    assert addresses_and_routes(hosts.namespace('second')) == (
        ['lo inet 127.0.0.1/8', 'lo inet6 ::1/128', f'eth0 inet {second}/24'],
        [f'{subnet}.0/24 dev eth0 proto kernel scope link src {second}'],
    )
    # The bridge's namespace has no address at all; nothing leads out of a host.
    assert addresses_and_routes(hosts.prefix) == ([], [])
    out = subprocess.run(
        ['ip', '-n', hosts.namespace('first'), 'route', 'get', '192.0.2.1'], capture_output=True
    )
    assert out.returncode != 0 and b'Network is unreachable' in out.stderr
    env = subprocess.run(
        [*hosts.command('first'), 'env'],
        env={**os.environ, 'ROS_HOSTNAME': 'x', 'ROS_MASTER_URI': 'http://m:1/'},
        capture_output=True,
        text=True,
        check=True,
    ).stdout.splitlines()
    assert f'ROS_IP={first}' in env and 'ROS_MASTER_URI=http://m:1/' in env
    assert not [line for line in env if line.startswith('ROS_HOSTNAME=')]


# The background job is the command once it has exec'd (before, its `ip -n` look-ups
# pass through the namespace too); the subprocess's timeout is the wait's deadline.
EXEC = """
source "$0"
HOSTS_PREFIX=$1
hosts_exec one sleep 30 &
until [ "$(tr '\\0' ' ' <"/proc/$!/cmdline")" = 'sleep 30 ' ]; do sleep 0.05; done
echo "background $! $(ip netns pids "$HOSTS_PREFIX-one")"
kill $!
hosts_exec one sh -c 'echo "on $ROS_IP"; exit 3' || echo "foreground status $?"
"""


@needs_namespaces
def test_exec_runs_in_the_background_as_the_command_itself_and_in_the_foreground_to_its_end(
    hosts: NetworkHosts,
):
    one = hosts.add('one')
    result = subprocess.run(
        ['bash', '-c', EXEC, str(HOSTS_SH), hosts.prefix], capture_output=True, text=True, timeout=30
    )
    background, *rest = result.stdout.splitlines()
    _, started, inside = background.split()
    assert started == inside  # $! is the command's pid: what run_scenario lists in DIR/pids
    assert rest == [f'on {one}', 'foreground status 3']


@needs_namespaces
def test_a_limited_link_has_a_tbf_at_both_ends(hosts: NetworkHosts):
    hosts.add('server')
    hosts.add('robot')
    hosts.limit('robot', '2mbit')

    def qdisc(namespace, device):
        return subprocess.run(
            ['tc', '-n', namespace, 'qdisc', 'show', 'dev', device],
            capture_output=True,
            text=True,
            check=True,
        ).stdout

    # The robot's number is 2: its end at the bridge is h2.
    for namespace, device in ((hosts.namespace('robot'), 'eth0'), (hosts.prefix, 'h2')):
        assert 'tbf' in qdisc(namespace, device) and 'rate 2Mbit' in qdisc(namespace, device)
    assert 'tbf' not in qdisc(hosts.namespace('server'), 'eth0')
    assert 'tbf' not in qdisc(hosts.prefix, 'h1')


@needs_namespaces
def test_nothing_remains_after_the_body_raised():
    with pytest.raises(RuntimeError, match='deliberate'), NetworkHosts() as made:
        made.add('one')
        made.add('two')
        assert len(made.leftovers()) == 3
        raise RuntimeError('deliberate')
    assert made.leftovers() == []
    assert root_links_of(made.prefix) == []


PYTHON_OWNER = """
import sys, time
from drvs.testing.netns import NetworkHosts
with NetworkHosts(sys.argv[1]) as made:
    made.add('one')
    made.add('two')
    time.sleep(600)
"""
# The pattern of scripts/run_scenario.sh: cleanup in the EXIT trap, signals exit through it;
# a long wait runs in the background (a trap waits for a foreground command to end).
BASH_OWNER = """
set -euo pipefail
source "$0"
trap hosts_cleanup EXIT
trap 'exit 130' INT TERM
hosts_init "$1"
hosts_add one >/dev/null
hosts_add two >/dev/null
sleep 600 &
wait $!
"""


@needs_namespaces
@pytest.mark.parametrize('owner', ['python', 'bash'])
@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM], ids=['SIGINT', 'SIGTERM'])
def test_nothing_remains_after_a_signal(owner, sig, tmp_path):
    prefix = f'dt{os.getpid()}s{sig.value}{owner[0]}'
    # SIGINT as it is in a terminal: a suite run in the background (`cmd &`) ignores it, and
    # a process that starts with it ignored can neither trap it (bash) nor get KeyboardInterrupt.
    argv = ['env', '--default-signal=INT']
    if owner == 'python':
        argv += [sys.executable, '-c', PYTHON_OWNER, prefix]
    else:
        argv += ['bash', '-c', BASH_OWNER, str(HOSTS_SH), prefix]
    env = {**os.environ, 'PYTHONPATH': str(REPO)}
    process = NodeProcess(owner, argv, env, tmp_path / 'owner.log', REPO)
    try:
        wait_for(
            lambda: len(namespaces_of(prefix)) == 3, 20, f'the hosts of {prefix}', on_timeout=process.describe
        )
        os.kill(process.pid, sig)
        process.process.wait(20)
        assert namespaces_of(prefix) == [], process.describe()
    finally:
        process.stop()
        hosts_call('hosts_cleanup', prefix=prefix)


@pytest.mark.parametrize(
    'call, message',
    [
        (
            ['hosts_init', 'a-b'],
            "hosts_init: prefix 'a-b' must be 1 to 24 letters, digits or _ "
            '(it starts every namespace name: PREFIX-HOST)',
        ),
        (['hosts_add', 'x'], 'hosts_add: no bridge: call hosts_init first'),
        (['hosts_ip', 'x'], 'hosts_ip: no bridge: call hosts_init first'),
        (
            ['hosts_limit', 'x', 'fast'],
            "hosts_limit: rate 'fast' must be a number with bit, kbit, mbit or gbit (e.g. 2mbit)",
        ),
    ],
)
def test_refusals_say_what_is_wrong(call, message):
    with pytest.raises(HostsError) as refused:
        hosts_call(*call)
    assert str(refused.value) == message


@needs_namespaces
@pytest.mark.parametrize(
    'call, message',
    [
        (['hosts_add', 'a.b'], "hosts_add: host name 'a.b' must be 1 to 32 letters, digits or _"),
        (['hosts_add', 'one'], 'hosts_add: host one exists already ({one})'),
        (['hosts_ip', 'three'], "hosts_ip: no host 'three' (hosts: one two)"),
        (['hosts_limit', 'three', '2mbit'], "hosts_limit: no host 'three' (hosts: one two)"),
        (['hosts_exec', 'three', 'true'], "hosts_exec: no host 'three' (hosts: one two)"),
    ],
)
def test_refusals_on_a_bridge_say_what_is_wrong(hosts: NetworkHosts, call, message):
    one = hosts.add('one')
    hosts.add('two')
    with pytest.raises(HostsError) as refused:
        hosts_call(*call, prefix=hosts.prefix)
    assert str(refused.value) == message.format(one=one)


@needs_namespaces
def test_a_prefix_in_use_is_refused_and_left_alone(hosts: NetworkHosts):
    with pytest.raises(HostsError) as refused, NetworkHosts(hosts.prefix):
        pass
    assert str(refused.value) == (
        f'hosts_init: namespaces of prefix {hosts.prefix} exist already '
        f"(another run's? HOSTS_PREFIX={hosts.prefix} hosts_cleanup removes them)"
    )
    assert hosts.leftovers() == [hosts.prefix]


def check(
    env: dict | None = None, user: list[str] = (), library: Path = HOSTS_SH
) -> subprocess.CompletedProcess:
    return subprocess.run(
        [*user, shutil.which('bash'), '-c', 'source "$0"; hosts_check', str(library)],
        env={**os.environ, **(env or {})},
        cwd=library.parent,
        capture_output=True,
        text=True,
    )


def test_check_names_a_missing_ip_command():
    result = check({'PATH': '/nonexistent'})
    assert (result.returncode, result.stdout) == (1, 'the ip command (iproute2) is not installed\n')


def test_check_names_a_missing_root():
    if os.geteuid() != 0:
        result, uid = check(), os.geteuid()
    else:  # as nobody, who may not read a checkout in root's home: a world-readable copy of the library
        with tempfile.TemporaryDirectory() as folder:
            os.chmod(folder, 0o755)
            library = Path(shutil.copy(HOSTS_SH, folder))
            os.chmod(library, 0o644)
            result = check(
                user=['setpriv', '--reuid=65534', '--regid=65534', '--clear-groups'], library=library
            )
        uid = 65534
    assert (result.returncode, result.stdout) == (1, f'network namespaces need root (running as uid {uid})\n')
