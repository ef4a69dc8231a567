"""Every statement of the PostgreSQL store is fixed text: values reach SQL only as bound parameters.

Read from the source (drvs/server/pg_store.py): a statement is a string literal, or an f-string
whose every interpolation is one of the module's constant SQL fragments (or, in ``clear``, a
table name from a literal tuple), or one of the constant ``SCHEMA`` statements; never a value.
The hostile-text test against a running server: test/live/test_registry_postgres.py.
"""

import ast
import inspect

import drvs.server.pg_store

FRAGMENTS = {'NOW', 'ENTRY_COLUMNS', 'table'}  # module constants; `table` loops over a literal tuple


def statements():
    tree = ast.parse(inspect.getsource(drvs.server.pg_store))
    for node in ast.walk(tree):
        if (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and node.func.attr == 'execute'
        ):
            if node.args:
                yield node.lineno, node.args[0]


def test_statements_are_literals_or_fstrings_of_constant_fragments():
    found = 0
    for line, statement in statements():
        found += 1
        if isinstance(statement, ast.Constant):
            assert isinstance(statement.value, str), line
            continue
        if isinstance(statement, ast.Name) and statement.id == 'statement':  # `for statement in SCHEMA`
            assert all(isinstance(text, str) for text in drvs.server.pg_store.SCHEMA)
            continue
        assert isinstance(statement, ast.JoinedStr), f'line {line}: a statement built at run time'
        for part in statement.values:
            if isinstance(part, ast.FormattedValue):
                assert (
                    isinstance(part.value, ast.Name) and part.value.id in FRAGMENTS
                ), f'line {line}: {ast.unparse(part.value)} is put into the SQL text'
    assert found >= 20  # the reader found the store's statements


def test_the_fragments_are_constants_and_tables_a_literal_tuple():
    assert isinstance(drvs.server.pg_store.NOW, str) and '%(now)s' in drvs.server.pg_store.NOW
    assert isinstance(drvs.server.pg_store.ENTRY_COLUMNS, str)
    source = inspect.getsource(drvs.server.pg_store.PgStore.clear)
    assert (
        "for table in ('drvs_vision_systems', 'drvs_ejections', 'drvs_watches', 'drvs_replicas'):" in source
    )
