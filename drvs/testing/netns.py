"""Separate network hosts for tests: scripts/hosts.sh, called from Python.

Every method runs one function of ``scripts/hosts.sh`` in a fresh bash, so the
shell library stays the only implementation. That works because the library keeps
its state in the kernel (namespace names): a bash with ``HOSTS_PREFIX`` set
continues where the last one stopped.

:class:`NetworkHosts` is a context manager: it makes the bridge on entry and
deletes every namespace of its prefix on exit, also when the body raised, on
Ctrl-C (KeyboardInterrupt) and on SIGTERM, which it turns into a
KeyboardInterrupt while it is open (unless someone else handles SIGTERM). Its
prefix is unique (pid and random), so parallel runs never meet.
Stop the processes started on the hosts before it closes (the ``ros`` fixture
does: request it after the hosts). Nothing here imports rospy.
"""

from __future__ import annotations

import os
import secrets
import signal
import subprocess
import threading

from drvs.testing.harness import REPO

HOSTS_SH = REPO / 'scripts' / 'hosts.sh'


class HostsError(RuntimeError):
    """A function of scripts/hosts.sh failed; the message is its one-line reason."""


def hosts_call(function: str, *args: str, prefix: str = '') -> str:
    """Run ``function args...`` of scripts/hosts.sh with ``HOSTS_PREFIX=prefix``; return its stdout.

    :raises HostsError: with its stderr, if it fails.
    """
    script = 'set -euo pipefail; source "$0"; HOSTS_PREFIX=$1; shift; "$@"'
    result = subprocess.run(
        ['bash', '-c', script, str(HOSTS_SH), prefix, function, *args],
        capture_output=True,
        text=True,
        timeout=30,
        stdin=subprocess.DEVNULL,
    )
    if result.returncode != 0:
        raise HostsError(result.stderr.strip() or f'{function} exited with {result.returncode}')
    return result.stdout


def unavailable() -> str | None:
    """Why hosts cannot be made here (for a skip), or None if they can."""
    result = subprocess.run(
        ['bash', '-c', 'source "$0" && hosts_check', str(HOSTS_SH)],
        capture_output=True,
        text=True,
        timeout=30,
    )
    if result.returncode == 0:
        return None
    return result.stdout.strip() or result.stderr.strip()


def namespaces_of(prefix: str) -> list[str]:
    """The network namespaces named ``prefix`` or ``prefix-...``, as ``ip netns list`` shows them."""
    listed = subprocess.run(['ip', 'netns', 'list'], capture_output=True, text=True, check=True).stdout
    names = [line.split()[0] for line in listed.splitlines() if line.strip()]
    return [name for name in names if name == prefix or name.startswith(prefix + '-')]


class NetworkHosts:
    """Hosts on one private bridge (see scripts/hosts.sh); deleted when the ``with`` block ends."""

    def __init__(self, prefix: str | None = None):
        self.prefix = prefix or f'dt{os.getpid()}r{secrets.token_hex(3)}'
        self._previous_sigterm = None

    def __enter__(self) -> NetworkHosts:
        if threading.current_thread() is threading.main_thread():
            if signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
                self._previous_sigterm = signal.signal(signal.SIGTERM, _interrupt)
        try:
            self._call('hosts_init', self.prefix)  # a refused or failed init leaves nothing of its own
        except BaseException:
            self._restore_sigterm()
            raise
        return self

    def __exit__(self, *exc) -> None:
        try:
            self.cleanup()
        finally:
            self._restore_sigterm()

    def _restore_sigterm(self) -> None:
        if self._previous_sigterm is not None:
            signal.signal(signal.SIGTERM, self._previous_sigterm)
            self._previous_sigterm = None

    def _call(self, function: str, *args: str) -> str:
        return hosts_call(function, *args, prefix=self.prefix).strip()

    def add(self, name: str) -> str:
        """Make host ``name`` (namespace PREFIX-name) on the bridge; return its address."""
        return self._call('hosts_add', name)

    def ip(self, name: str) -> str:
        return self._call('hosts_ip', name)

    def limit(self, name: str, rate: str) -> None:
        """Limit the host's link to ``rate`` (tc tbf, e.g. ``2mbit``) in both directions."""
        self._call('hosts_limit', name, rate)

    def command(self, name: str) -> list[str]:
        """The words to put before a command to run it on host ``name`` (with its ROS_IP)."""
        return self._call('hosts_command', name).splitlines()

    def cleanup(self) -> None:
        """Delete every namespace of this prefix, and so every link; nothing if there is none."""
        self._call('hosts_cleanup')

    def namespace(self, name: str) -> str:
        return f'{self.prefix}-{name}'

    def leftovers(self) -> list[str]:
        """The namespaces of this prefix that still exist."""
        return namespaces_of(self.prefix)


def _interrupt(signum, frame):
    raise KeyboardInterrupt(f'signal {signal.Signals(signum).name}')
