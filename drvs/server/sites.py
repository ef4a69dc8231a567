"""Sites: servers on separate ROS masters sharing one registry database, and what crosses between them.

Each entry of the registry records the site (``~site``) of the server it registered through. A
vision system of another site is not known to this server's master: the server calls it at the
``rosrpc://`` address it registered with (:func:`direct_uri`), and tells it where the robot's
callback service is (:func:`callback_uri`), which the vision system's master does not know either.
Same-site entries go through the master as before. No ROS here; how to run sites and what the
network must allow: docs/registry.md ("Sites").

>>> direct_uri('a', 'b', 'rosrpc://cam-b:40111'), direct_uri('a', 'a', 'rosrpc://cam-a:40222')
('rosrpc://cam-b:40111', None)
>>> callback_uri('a', 'b', 'rosrpc://robot-a:39001'), callback_uri('a', 'a', 'rosrpc://robot-a:39001')
('rosrpc://robot-a:39001', '')
"""

from __future__ import annotations

import re

from drvs.common.status import INVALID, UNAVAILABLE, Refusal

__all__ = [
    'MAX_SITE_LENGTH',
    'SITE_PATTERN',
    'callback_uri',
    'direct_uri',
    'other_site',
    'remote',
    'requested_callback_uri',
    'site_name',
]

SITE_PATTERN = re.compile(r'[A-Za-z0-9_-]*')
MAX_SITE_LENGTH = 64


def site_name(site: str) -> str:
    """``site`` if it is a valid ``~site``: up to 64 letters, digits, ``_`` or ``-`` ('' = the only site).

    >>> site_name('hall-b')
    'hall-b'
    >>> site_name('hall b')
    Traceback (most recent call last):
    ...
    ValueError: must be letters, digits, _ or -, at most 64 of them, got 'hall b'
    """
    if len(site) > MAX_SITE_LENGTH or not SITE_PATTERN.fullmatch(site):
        raise ValueError(f'must be letters, digits, _ or -, at most {MAX_SITE_LENGTH} of them, got {site!r}')
    return site


def remote(our_site: str, entry_site: str) -> bool:
    """Whether an entry registered at ``entry_site`` is at another site than this server's."""
    return entry_site != our_site


def direct_uri(our_site: str, entry_site: str, instance: str) -> str | None:
    """Where to call a vision system registered at ``entry_site`` with the address ``instance``:
    that address when it is at another site (our master does not know it), None when it is at
    ours (its name is looked up on our master, as without sites)."""
    return instance if remote(our_site, entry_site) else None


def callback_uri(our_site: str, entry_site: str, resolved: str) -> str:
    """The ``callback_uri`` of a forward to a vision system at ``entry_site``: ``resolved`` (the
    callback service's address on our master) when it is at another site, else '' (the vision
    system looks the callback service up on its master, which is ours)."""
    return resolved if remote(our_site, entry_site) else ''


def requested_callback_uri(value: str) -> None:
    """A caller of the server leaves ``callback_uri`` empty: the server fills it, for vision systems
    at other sites, with an address it resolved itself.

    :raises Refusal: ``INVALID`` naming the field.
    """
    if value:
        raise Refusal(
            INVALID,
            f'callback_uri: {value[:80]!r}; leave it empty in a call to the DRVS server '
            '(it fills it for vision systems at other sites)',
        )


def other_site(service_name: str, site: str, left: float) -> Refusal:
    """The refusal of a registration of ``service_name`` while the same name is registered at
    ``site`` (another site) for ``left`` seconds more."""
    return Refusal(
        UNAVAILABLE,
        f'service_name: {service_name} is registered at site {site or "(unnamed)"} '
        f'for {max(left, 0.0):.1f} s more; vision systems at different sites need different names '
        '(give each a namespace of its own)',
        max(left, 0.1),
    )
