"""Request bodies and queries of the gateway: every problem a 400 naming the field, word for word."""

import pytest

from drvs.gateway.body import (
    BadRequest,
    DetectBody,
    WatchBody,
    detect_body,
    json_body,
    region_query,
    watch_body,
)

REGION = {'min_x': 0, 'min_y': 0, 'max_x': 2, 'max_y': 1}
COLOUR = 'colour:0,0,150,80,80,255'


def test_a_full_detect_and_watch_body():
    body = {'algorithm': COLOUR, 'region': REGION, 'wait': 1.5, 'fused': True}
    assert detect_body(body) == DetectBody(COLOUR, (0.0, 0.0, 2.0, 1.0), 1.5, True)
    watch = {'algorithm': 'motion', 'region': REGION, 'period': 0.5, 'changes_only': True}
    assert watch_body(watch) == WatchBody('motion', (0.0, 0.0, 2.0, 1.0), 0.5, True, False)


@pytest.mark.parametrize(
    ('raw', 'message'),
    [
        (b'', 'body: empty; expected a JSON object'),
        (b'{"a": ', 'body: not JSON: Expecting value at line 1 column 7'),
        (b'[1, 2]', 'body: expected a JSON object, got an array'),
        (b'{"wait": NaN}', 'body: NaN is not JSON'),
        (b'\xff{}', 'body: not UTF-8 (byte 0)'),
        (b'[' * 100_000, 'body: nested too deeply'),
    ],
)
def test_bodies_that_are_not_a_json_object(raw, message):
    with pytest.raises(BadRequest) as caught:
        json_body(raw)
    assert (str(caught.value), caught.value.field) == (message, 'body')


@pytest.mark.parametrize(
    ('change', 'field', 'message'),
    [
        ({'colour': 1}, 'colour', 'colour: unknown field; expected algorithm, region, wait, fused'),
        ({'algorithm': None}, 'algorithm', 'algorithm: expected a string NAME:PARAMS, got null'),
        ({'algorithm': 'colour:1,2'}, 'algorithm', None),
        ({'region': [0, 0, 1, 1]}, 'region', None),
        (
            {'region': {**REGION, 'min_x': '0'}},
            'region.min_x',
            'region.min_x: expected a number, got a string',
        ),
        ({'region': {**REGION, 'max_z': 1}}, 'region.max_z', None),
        ({'region': {'min_x': 0}}, 'region.min_y', 'region.min_y: missing'),
        ({'region': {**REGION, 'min_x': 5}}, 'region', 'region: min_x 5 is greater than max_x 2'),
        ({'region': {**REGION, 'max_x': 1e300}}, 'region', None),
        ({'wait': True}, 'wait', 'wait: expected a number, got a boolean'),
        ({'wait': -1}, 'wait', 'wait: -1 s; expected 0 to 30 s'),
        ({'fused': 'yes'}, 'fused', 'fused: expected true or false, got a string'),
    ],
)
def test_detect_bodies_refused_naming_the_field(change, field, message):
    body = {'algorithm': COLOUR, 'region': REGION, **change}
    with pytest.raises(BadRequest) as caught:
        detect_body(body)
    assert caught.value.field == field
    if message:
        assert str(caught.value) == message


def test_missing_fields_and_watch_fields():
    with pytest.raises(BadRequest, match='^region: missing$'):
        detect_body({'algorithm': COLOUR})
    with pytest.raises(BadRequest, match=r'^period: 0 s; expected more than 0, at most 3600 s$'):
        watch_body({'algorithm': COLOUR, 'region': REGION, 'period': 0})
    with pytest.raises(BadRequest, match='^wait: unknown field'):
        watch_body({'algorithm': COLOUR, 'region': REGION, 'wait': 1})


def test_a_plugin_algorithm_is_checked_for_syntax_only():
    assert (
        detect_body({'algorithm': 'someplugin:anything', 'region': REGION}).algorithm == 'someplugin:anything'
    )
    with pytest.raises(BadRequest) as caught:
        detect_body({'algorithm': '9bad', 'region': REGION})
    assert caught.value.field == 'algorithm'


def test_region_query():
    assert region_query({'min_x': '0', 'min_y': '0', 'max_x': '1', 'max_y': '2'}) == (0.0, 0.0, 1.0, 2.0)
    with pytest.raises(BadRequest, match=r"^min_x: expected a number, got 'a'$"):
        region_query({'min_x': 'a', 'min_y': '0', 'max_x': '1', 'max_y': '2'})
    with pytest.raises(BadRequest, match='^limit: unknown field'):
        region_query({'min_x': '0', 'min_y': '0', 'max_x': '1', 'max_y': '2', 'limit': '3'})
    with pytest.raises(BadRequest, match='^max_y: missing$'):
        region_query({'min_x': '0', 'min_y': '0', 'max_x': '1'})
