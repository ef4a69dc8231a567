"""Bearer tokens: a file of salted hashes, each with the operations and algorithm names it may use.

A token is ``drvs.<id>.<secret>``: the id finds its entry, the secret is checked against the
entry's salted scrypt hash in constant time. The file never holds a token, only its hash, so
reading the file does not let anyone in; a token is shown once, when it is made
(``drvs_token add``). Verified tokens are remembered (a bounded cache keyed by a keyed hash), so
the key derivation is paid once per token, not per request. The rules: docs/gateway.md ("Tokens").

>>> tokens = Tokens([])
>>> token, entry = make_entry('dashboard', ops=['read'], cost=2**4)
>>> tokens = Tokens([entry])
>>> grant = tokens.authenticate(f'Bearer {token}')
>>> grant.name, grant.may('read'), grant.may('detect', 'colour:0,0,150,80,80,255')
('dashboard', True, False)
"""

from __future__ import annotations

import hashlib
import hmac
import json
import os
import secrets
import tempfile
from collections import OrderedDict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = [
    'OPERATIONS',
    'Forbidden',
    'Grant',
    'TokenFileError',
    'Tokens',
    'Unauthorized',
    'add_token',
    'load_tokens',
    'make_entry',
    'read_entries',
    'remove_token',
]

OPERATIONS = ('detect', 'watch', 'read')
"""What a token may do: ``detect`` (POST /v1/detect), ``watch`` (the watches and their events),
``read`` (vision systems, coverage, objects, health)."""
ANY = '*'
"""In a token's algorithms: every algorithm."""
PREFIX = 'drvs'
COST = 2**12
"""scrypt's n for new tokens (r 8, p 1: 4 MiB and a few ms per check; the secret is 256 random bits,
so a slow hash guards a stolen file, not a guessable password)."""
CACHE = 1024
"""Verified tokens remembered."""


class Unauthorized(Exception):
    """No token, or one the gateway does not know (HTTP 401)."""


class Forbidden(Exception):
    """A known token used outside its rights (HTTP 403)."""


class TokenFileError(ValueError):
    """A tokens file that cannot be used; the message names the file and the problem."""


@dataclass(frozen=True)
class Grant:
    """What one token may do: its ``name``, ``ops`` and ``algorithms`` (names; ``*`` = any)."""

    name: str
    ops: frozenset[str]
    algorithms: frozenset[str]

    def may(self, op: str, algorithm: str | None = None) -> bool:
        """Whether the token may do ``op`` (with the algorithm string ``algorithm``)."""
        if op not in self.ops:
            return False
        if algorithm is None or ANY in self.algorithms:
            return True
        return algorithm.partition(':')[0] in self.algorithms

    def check(self, op: str, algorithm: str | None = None) -> None:
        """:raises Forbidden: naming the token and what it may not do."""
        if op not in self.ops:
            raise Forbidden(
                f'token {self.name!r} may not {op} (it may {", ".join(sorted(self.ops)) or "nothing"})'
            )
        if not self.may(op, algorithm):
            name = (algorithm or '').partition(':')[0]
            raise Forbidden(
                f'token {self.name!r} may not use the algorithm {name!r} '
                f'(it may use {", ".join(sorted(self.algorithms))})'
            )


OPEN = Grant('', frozenset(OPERATIONS), frozenset({ANY}))
"""The rights of every client of a gateway without tokens (loopback only)."""


def _hash(secret: str, salt: bytes, cost: int) -> bytes:
    return hashlib.scrypt(secret.encode(), salt=salt, n=cost, r=8, p=1, maxmem=64 * 1024 * 1024, dklen=32)


def _checked_names(field: str, values: Iterable[str], allowed: Sequence[str] | None) -> list[str]:
    names = sorted({value.strip() for value in values if value.strip()})
    for value in names:
        if allowed is not None and value not in allowed:
            raise ValueError(f'{field}: unknown {value!r}; expected some of {", ".join(allowed)}')
        if allowed is None and value != ANY and not value.replace('_', '').isalnum():
            raise ValueError(f'{field}: {value!r} is not an algorithm name (letters, digits, _) or *')
    return names


def make_entry(
    name: str,
    ops: Iterable[str] = OPERATIONS,
    algorithms: Iterable[str] = (ANY,),
    cost: int = COST,
) -> tuple[str, dict[str, Any]]:
    """A new token and its file entry (``name``, ``id``, ``salt``, ``n``, ``hash``, ``ops``,
    ``algorithms``).

    :raises ValueError: an empty name, an unknown operation or a malformed algorithm name.
    """
    if not name or not name.strip():
        raise ValueError('name: empty')
    ops = _checked_names('ops', ops, OPERATIONS)
    algorithms = _checked_names('algorithms', algorithms, None) or [ANY]
    token_id, secret, salt = secrets.token_hex(6), secrets.token_urlsafe(32), os.urandom(16)
    entry = {
        'name': name.strip(),
        'id': token_id,
        'salt': salt.hex(),
        'n': cost,
        'hash': _hash(secret, salt, cost).hex(),
        'ops': ops,
        'algorithms': algorithms,
    }
    return f'{PREFIX}.{token_id}.{secret}', entry


class Tokens:
    """The tokens of one file: :meth:`authenticate` a request's ``Authorization`` header.

    Thread-safe enough for one event loop (no locks: called from the loop's thread only).
    """

    def __init__(self, entries: Iterable[dict[str, Any]]):
        self._entries = {entry['id']: entry for entry in entries}
        self._key = os.urandom(32)
        self._verified: OrderedDict[bytes, Grant] = OrderedDict()
        self.checks = 0  # key derivations run (a cache miss each)

    def __len__(self) -> int:
        return len(self._entries)

    def authenticate(self, authorization: str | None) -> Grant:
        """The grant of the token in ``Authorization: Bearer TOKEN``.

        :raises Unauthorized: no header, not ``Bearer``, malformed, or no such token.
        """
        if not authorization:
            raise Unauthorized('no token: send the header Authorization: Bearer TOKEN')
        scheme, _, token = authorization.strip().partition(' ')
        if scheme.lower() != 'bearer' or not token.strip():
            raise Unauthorized('expected the header Authorization: Bearer TOKEN')
        token = token.strip()
        digest = hmac.new(self._key, token.encode(errors='replace'), hashlib.sha256).digest()
        grant = self._verified.get(digest)
        if grant is not None:
            self._verified.move_to_end(digest)
            return grant
        prefix, _, rest = token.partition('.')
        token_id, _, secret = rest.partition('.')
        entry = self._entries.get(token_id)
        if prefix != PREFIX or entry is None or not secret:
            raise Unauthorized('unknown token')
        self.checks += 1
        if not hmac.compare_digest(
            _hash(secret, bytes.fromhex(entry['salt']), entry['n']), bytes.fromhex(entry['hash'])
        ):
            raise Unauthorized('unknown token')
        grant = Grant(entry['name'], frozenset(entry['ops']), frozenset(entry['algorithms']))
        self._verified[digest] = grant
        while len(self._verified) > CACHE:
            self._verified.popitem(last=False)
        return grant


_ENTRY_FIELDS = {'name': str, 'id': str, 'salt': str, 'n': int, 'hash': str, 'ops': list, 'algorithms': list}


def read_entries(path: str | Path) -> list[dict[str, Any]]:
    """The entries of the tokens file ``path`` (none when it does not exist).

    :raises TokenFileError: not JSON, or an entry without its fields.
    """
    path = Path(path)
    if not path.exists():
        return []
    try:
        document = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise TokenFileError(f'{path}: cannot read the tokens file: {error}') from None
    entries = document.get('tokens') if isinstance(document, dict) else None
    if not isinstance(entries, list):
        raise TokenFileError(f'{path}: expected {{"tokens": [...]}} (made by drvs_token add)')
    for i, entry in enumerate(entries):
        for field, kind in _ENTRY_FIELDS.items():
            if not isinstance(entry, dict) or not isinstance(entry.get(field), kind):
                raise TokenFileError(f'{path}: tokens[{i}].{field}: missing or not a {kind.__name__}')
        unknown = set(entry['ops']) - set(OPERATIONS)
        if unknown:
            raise TokenFileError(f'{path}: tokens[{i}].ops: unknown {", ".join(sorted(unknown))}')
    return entries


def load_tokens(path: str | Path) -> Tokens:
    """The tokens of the file ``path``, which must exist.

    :raises TokenFileError: as :func:`read_entries`, or no such file.
    """
    if not Path(path).is_file():
        raise TokenFileError(f'{path}: no such tokens file (make one with drvs_token add NAME --file {path})')
    return Tokens(read_entries(path))


def _write(path: Path, entries: list[dict[str, Any]]) -> None:
    """Write atomically, readable by the owner only."""
    text = json.dumps({'tokens': entries}, indent=1) + '\n'
    folder = path.parent if str(path.parent) else Path('.')
    handle, temporary = tempfile.mkstemp(dir=folder, prefix=f'.{path.name}.')
    try:
        with os.fdopen(handle, 'w') as out:
            out.write(text)
        os.chmod(temporary, 0o600)
        os.replace(temporary, path)
    except BaseException:
        os.unlink(temporary)
        raise


def add_token(
    path: str | Path, name: str, ops: Iterable[str] = OPERATIONS, algorithms: Iterable[str] = (ANY,)
) -> str:
    """Add a token named ``name`` to the file ``path`` (made if missing); return the token (shown once).

    :raises ValueError: a name the file has already, or as :func:`make_entry`.
    :raises TokenFileError: as :func:`read_entries`.
    """
    path = Path(path)
    entries = read_entries(path)
    if any(entry['name'] == name for entry in entries):
        raise ValueError(f'name: {path} has a token named {name!r} already (remove it first)')
    token, entry = make_entry(name, ops, algorithms)
    _write(path, [*entries, entry])
    return token


def remove_token(path: str | Path, name: str) -> bool:
    """Remove the token named ``name`` from ``path``; False if there was none."""
    path = Path(path)
    entries = read_entries(path)
    kept = [entry for entry in entries if entry['name'] != name]
    if len(kept) == len(entries):
        return False
    _write(path, kept)
    return True
