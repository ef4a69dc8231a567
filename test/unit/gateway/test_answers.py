"""DRVS status -> HTTP: each code, its body and Retry-After."""

import pytest

from drvs.common.status import BUSY, INVALID, RATE_LIMITED, UNAVAILABLE, UNSUPPORTED
from drvs.gateway import answers


@pytest.mark.parametrize(
    ('status', 'http', 'retry'),
    [
        (INVALID, 400, None),
        (UNSUPPORTED, 422, None),
        (RATE_LIMITED, 429, '3'),
        (BUSY, 503, '3'),
        (UNAVAILABLE, 503, '3'),
    ],
)
def test_every_refusal_has_its_http_status(status, http, retry):
    answer = answers.refusal(
        status, 'algorithm: no vision system runs blob', 2.5, ['motion', 'colour', 'motion']
    )
    assert answer.status == http
    assert answer.headers.get('Retry-After') == retry
    assert answer.body['message'] == 'algorithm: no vision system runs blob'
    if status == UNSUPPORTED:
        assert answer.body['available_algorithms'] == ['colour', 'motion']


@pytest.mark.parametrize(
    ('message', 'field'),
    [
        ('region_of_interest: min_x 2 is greater than max_x 1', 'region'),
        ('algorithm: unknown NAME blob', 'algorithm'),
        ('something odd', 'body'),
    ],
)
def test_invalid_names_the_gateway_field(message, field):
    assert answers.refusal(INVALID, message, 0).body == {
        'error': 'INVALID',
        'message': message,
        'field': field,
    }


def test_no_server_unauthorized_forbidden_and_unknown_codes():
    assert answers.no_server('timed out after 2 s', 1.0).status == 503
    assert answers.no_server('timed out after 2 s', 1.0).headers == {'Retry-After': '1'}
    assert answers.unauthorized('no token').headers['WWW-Authenticate'].startswith('Bearer')
    assert answers.forbidden('no').status == 403
    assert answers.refusal(9, 'new code', 0).status == 502
