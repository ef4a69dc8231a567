"""What a running process holds, for the hostile-input tests: its resident memory and its
established TCP connections on one local port (docs/gateway.md, "Limits")."""

from __future__ import annotations

import psutil

__all__ = ['MIB', 'established', 'rss']

MIB = 1024 * 1024


def rss(pid: int) -> int:
    """Resident memory of ``pid`` in bytes (``VmRSS`` of /proc/PID/status)."""
    return psutil.Process(pid).memory_info().rss


def established(pid: int, port: int) -> int:
    """TCP connections of ``pid`` established on its local ``port`` (a server's accepted ones)."""
    return sum(
        1
        for each in psutil.Process(pid).connections(kind='tcp')
        if each.status == psutil.CONN_ESTABLISHED and each.laddr.port == port
    )
