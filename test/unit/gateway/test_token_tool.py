"""drvs_token: add prints the token once, list shows rights, remove takes one out; exit codes."""

from drvs.gateway.tokens import load_tokens
from drvs.tools.token import main


def test_add_list_remove(tmp_path, capsys):
    path = str(tmp_path / 'tokens.json')
    assert main(['add', 'robot', '--file', path, '--ops', 'detect,watch', '--algorithms', 'colour']) == 0
    token = capsys.readouterr().out.strip()
    assert load_tokens(path).authenticate(f'Bearer {token}').ops == {'detect', 'watch'}
    assert main(['list', '--file', path]) == 0
    assert capsys.readouterr().out == 'robot\tops detect,watch\talgorithms colour\n'
    assert main(['add', 'robot', '--file', path]) == 2
    assert "has a token named 'robot' already" in capsys.readouterr().err
    assert main(['remove', 'robot', '--file', path]) == 0
    assert main(['remove', 'robot', '--file', path]) == 1
