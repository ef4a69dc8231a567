"""Fixtures of the live tests (a private master each, from the suite's conftest)."""

import pytest


@pytest.fixture
def make_graph(ros, monkeypatch, tmp_path):
    """``make(**server_params)``: a server with fake cameras on the test's master
    (:class:`test_server.Graph`), closed at teardown; for the server and security tests."""
    from test_server import Graph

    made = []

    def make(**params):
        made.append(Graph(ros, monkeypatch, tmp_path, **params))
        return made[-1]

    yield make
    for graph in made:
        graph.close()
