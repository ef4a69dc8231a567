"""Tokens: the file keeps salted hashes only; 401 for no or unknown tokens, 403 outside the rights."""

import json
import stat

import pytest

from drvs.gateway.tokens import (
    Forbidden,
    TokenFileError,
    Tokens,
    Unauthorized,
    add_token,
    load_tokens,
    make_entry,
    read_entries,
    remove_token,
)

CHEAP = 2**4  # scrypt's n in tests: the file's format, not its cost


def test_add_keeps_only_a_salted_hash_readable_by_the_owner(tmp_path):
    path = tmp_path / 'tokens.json'
    token = add_token(path, 'robot', ops=['detect'], algorithms=['colour'])
    text = path.read_text()
    assert token.startswith('drvs.') and token.split('.')[2] not in text
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    (entry,) = json.loads(text)['tokens']
    assert (entry['name'], entry['ops'], entry['algorithms']) == ('robot', ['detect'], ['colour'])
    grant = load_tokens(path).authenticate(f'Bearer {token}')
    assert grant.may('detect', 'colour:0,0,150,80,80,255') and not grant.may('detect', 'motion')
    with pytest.raises(ValueError, match="has a token named 'robot' already"):
        add_token(path, 'robot')
    assert remove_token(path, 'robot') and read_entries(path) == [] and not remove_token(path, 'robot')


@pytest.mark.parametrize(
    ('header', 'message'),
    [
        (None, 'no token: send the header Authorization: Bearer TOKEN'),
        ('Basic dXNlcjpwYXNz', 'expected the header Authorization: Bearer TOKEN'),
        ('Bearer drvs.000000000000.secret', 'unknown token'),
        ('Bearer garbage', 'unknown token'),
    ],
)
def test_no_or_unknown_tokens_are_unauthorized(header, message):
    tokens = Tokens([make_entry('robot', cost=CHEAP)[1]])
    with pytest.raises(Unauthorized, match=f'^{message}$'):
        tokens.authenticate(header)


def test_a_wrong_secret_is_unauthorized_and_a_right_one_checked_once():
    token, entry = make_entry('robot', cost=CHEAP)
    tokens = Tokens([entry])
    with pytest.raises(Unauthorized):
        tokens.authenticate(f'Bearer {token[:-1]}x' if not token.endswith('x') else f'Bearer {token[:-1]}y')
    for _ in range(3):
        assert tokens.authenticate(f'Bearer {token}').name == 'robot'
    assert tokens.checks == 2  # the wrong one, then the right one once: remembered after


def test_rights_are_checked_by_operation_and_algorithm_name():
    token, entry = make_entry('viewer', ops=['read'], algorithms=['motion', 'apriltag'], cost=CHEAP)
    grant = Tokens([entry]).authenticate(f'Bearer {token}')
    grant.check('read')
    with pytest.raises(Forbidden, match="^token 'viewer' may not detect \\(it may read\\)$"):
        grant.check('detect')
    grant = Tokens([make_entry('robot', ops=['detect'], algorithms=['motion'], cost=CHEAP)[1]])
    robot = make_entry('robot', ops=['detect'], algorithms=['motion'], cost=CHEAP)
    grant = Tokens([robot[1]]).authenticate(f'Bearer {robot[0]}')
    grant.check('detect', 'motion')
    with pytest.raises(
        Forbidden, match="^token 'robot' may not use the algorithm 'colour' \\(it may use motion\\)$"
    ):
        grant.check('detect', 'colour:0,0,150,80,80,255')


@pytest.mark.parametrize(
    ('kwargs', 'message'),
    [
        ({'ops': ['fly']}, "ops: unknown 'fly'; expected some of detect, watch, read"),
        ({'algorithms': ['col our']}, "algorithms: 'col our' is not an algorithm name"),
    ],
)
def test_bad_rights_are_refused_when_made(kwargs, message):
    with pytest.raises(ValueError, match=message):
        make_entry('x', cost=CHEAP, **kwargs)


def test_broken_files_are_named(tmp_path):
    path = tmp_path / 'tokens.json'
    with pytest.raises(TokenFileError, match='no such tokens file'):
        load_tokens(path)
    path.write_text('{"tokens": [{"name": "a"}]}')
    with pytest.raises(TokenFileError, match=r'tokens\[0\]\.id: missing or not a str'):
        load_tokens(path)
    path.write_text('nonsense')
    with pytest.raises(TokenFileError, match='cannot read the tokens file'):
        load_tokens(path)
