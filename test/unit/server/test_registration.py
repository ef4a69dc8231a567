"""Who may register, move, renew or unregister which vision system (no ROS: the master is a fake)."""

import pytest

from drvs.common.status import INVALID, UNAVAILABLE, Refusal
from drvs.server.registration import Registered, Registrar
from drvs.server.registry import CHANGED, MOVED, REGISTERED, Registry
from drvs.testing import ManualClock

SERVICE = '/vs1/detect_object_boundary'
SQUARE = [(0.0, 0.0), (2.0, 0.0), (2.0, 2.0), (0.0, 2.0)]


class Master:
    """A fake ``verify``: the provider of each service, and what it was asked."""

    def __init__(self):
        self.providers = {SERVICE: '/vs1'}
        self.asked = []
        self.instance = 'rosrpc://host:1'

    def __call__(self, service, provider):
        self.asked.append((service, provider))
        if self.providers.get(service) != provider:
            raise Refusal(INVALID, f'service_name: {service} is provided by someone else')
        return self.instance, True


class Registrations:
    def __init__(self):
        self.master = Master()
        self.registry = Registry(lease=10.0, clock=ManualClock())
        self.changes = []
        self.removed = []
        self.registrar = Registrar(
            self.registry,
            '/drvs',
            self.master,
            make_client=lambda service, uri: None,
            on_change=lambda change, service: self.changes.append((change, service)),
            on_removed=self.removed.append,
        )

    def register(self, points=SQUARE, algorithms=(), caller='/vs1', service=SERVICE):
        return self.registrar.register(service, points, algorithms, caller)


@pytest.fixture
def desk():
    return Registrations()


def refusal(call) -> Refusal:
    with pytest.raises(Refusal) as refused:
        call()
    return refused.value


def test_a_registration_asks_the_master_once_then_renewals_and_moves_do_not(desk):
    assert desk.register() == Registered(f'registered {SERVICE}; lease 10 s', 10.0)
    assert desk.registry.get(SERVICE).instance == 'rosrpc://host:1'
    assert desk.registry.get(SERVICE).watch_service
    assert desk.register() == Registered(f'renewed {SERVICE}; lease 10 s', 10.0)
    assert desk.register(points=SQUARE[:3]).message == f'moved {SERVICE}; lease 10 s'
    assert desk.register(points=SQUARE[:3], algorithms=['sift']).message == f'changed {SERVICE}; lease 10 s'
    assert desk.master.asked == [(SERVICE, '/vs1')]
    assert desk.changes == [(REGISTERED, SERVICE), (MOVED, SERVICE), (CHANGED, SERVICE)]  # not the renewal
    assert desk.registry.get(SERVICE).algorithms == frozenset({'sift'})


def test_the_server_itself_may_not_register(desk):
    refused = refusal(lambda: desk.register(caller='/drvs'))
    assert (refused.status, refused.message) == (
        INVALID,
        'service_name: the caller /drvs is the DRVS server itself; forwarding to it would loop',
    )
    assert desk.master.asked == []


def test_another_node_is_asked_about_and_refused(desk):
    desk.register()
    refused = refusal(lambda: desk.register(caller='/intruder'))
    assert refused.message == f'service_name: {SERVICE} is provided by someone else'
    assert desk.master.asked[-1] == (SERVICE, '/intruder')
    assert desk.registry.get(SERVICE).provider == '/vs1'


def test_a_caller_without_caller_id_is_asked_about_as_such(desk):
    refusal(lambda: desk.register(caller=''))
    assert desk.master.asked == [(SERVICE, '(no caller id)')]


@pytest.mark.parametrize(
    ('points', 'algorithms', 'message'),
    [
        ([(0, 0), (1, 1)], (), 'field_of_view: 2 vertices; a polygon needs at least 3'),
        (
            SQUARE,
            ['not a name'],
            "algorithms[0]: 'not a name' is not an algorithm NAME "
            '(a letter, then letters, digits or _, without :PARAMS)',
        ),
    ],
)
def test_an_invalid_field_of_view_or_algorithm_names_the_service(desk, points, algorithms, message):
    refused = refusal(lambda: desk.register(points=points, algorithms=algorithms))
    assert (refused.status, refused.message) == (INVALID, f'{message} (service_name {SERVICE})')
    assert desk.master.asked == []


def test_only_the_provider_may_unregister(desk):
    desk.register()
    refused = refusal(lambda: desk.register(points=[], caller='/other'))
    assert refused.message == f'service_name: {SERVICE} was registered by /vs1; /other may not unregister it'
    assert desk.register(points=[]) == Registered(f'unregistered {SERVICE}')
    assert [entry.service_name for entry in desk.removed] == [SERVICE]
    assert desk.register(points=[]) == Registered(f'not registered: {SERVICE}')
    assert len(desk.removed) == 1


def test_an_ejected_vision_system_is_refused_by_the_registry(desk):
    desk.register()
    for _ in range(3):
        desk.registry.record_failure(SERVICE)
    assert refusal(lambda: desk.register()).status == UNAVAILABLE  # the same instance
    # A restarted vision system (a new instance) may register at once.
    desk.master.instance = 'rosrpc://host:2'
    assert desk.register().message == f'registered {SERVICE}; lease 10 s'
