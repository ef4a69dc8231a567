"""Read a node's private ``~parameters`` into its settings dataclass, one way for every node.

Every field of the dataclass is a parameter of the same name, declared with
:func:`drvs.common.settings.param`. A field without a default is required. Values are
checked against the field's type (an int is accepted where a float is expected;
``None`` defaults accept a number or nothing), so a typo on the command line is
refused with a message naming the parameter instead of failing later; building
the dataclass then checks the declared ranges (:func:`drvs.common.settings.check`).
Every problem is reported at once, one line per parameter (:class:`drvs.common.settings.ParamError`).

Where a wrong value came from matters: rospy puts the command line's
``_name:=value`` on the parameter server at ``init_node``, so a value on the
server that this command line does not give was left there before the node
started (an earlier run, a launch file, ``rosparam set``); its error says so and
how to clear it (:func:`origin_note`). Private parameters the node does not know
are not errors but are warned about, with the nearest known name
(:func:`unknown_param_warnings`).

>>> origin_note('/world_sim', 'rate')
' (from the parameter server, not from this command line: left by an earlier run, \
a launch file or `rosparam set`; clear it with `rosparam delete /world_sim/rate`)'
"""

from __future__ import annotations

import dataclasses
import difflib
import sys
import tempfile
from collections.abc import Callable, Collection, Iterable, Mapping
from pathlib import Path

import yaml

from drvs.common.settings import ParamError, checked

__all__ = [
    'command_line_params',
    'origin_note',
    'private_param_names',
    'read_params',
    'unknown_param_warnings',
    'writable_folder',
]

_MISSING = object()


def _joined(field: dataclasses.Field, value):
    """A list given for a ``str`` field declared with a separator, joined; anything else unchanged."""
    separator = field.metadata.get('separator')
    if not separator or not isinstance(value, list):
        return value
    if not all(isinstance(item, str) for item in value):
        raise ParamError(field.name, f'expected a string or a list of strings, got {value!r}')
    return separator.join(value)


def origin_note(node: str, name: str) -> str:
    """What an error adds about a value of ``node``'s ``~name`` that is not from its command line."""
    return (
        ' (from the parameter server, not from this command line: left by an earlier run, a launch file '
        f'or `rosparam set`; clear it with `rosparam delete {node}/{name}`)'
    )


def command_line_params(argv: list[str] | None = None) -> dict[str, object]:
    """The private parameters ``_name:=value`` of ``argv`` (default ``sys.argv``), read as rospy does.

    >>> command_line_params(['node', '_rate:=2', '__name:=n', 'a:=b', '_cameras:=[vs1, vs2]'])
    {'rate': 2, 'cameras': ['vs1', 'vs2']}

    :raises ParamError: naming a value that is not YAML (rospy would raise at ``init_node``).
    """
    import rosgraph.names

    params = {}
    for arg in sys.argv if argv is None else argv:
        if not rosgraph.names.is_legal_remap(arg):
            continue
        name, value = (part.strip() for part in arg.split(':=', 1))
        if len(name) < 2 or name[0] != '_' or name[1] == '_' or not value:
            continue
        try:
            params[name[1:]] = yaml.safe_load(value)
        except yaml.YAMLError as error:
            problem = getattr(error, 'problem', None) or str(error).splitlines()[0]
            raise ParamError(name[1:], f'cannot read {value!r} as YAML ({problem})') from None
    return params


def read_params(
    cls,
    defaults: Mapping[str, object] | None = None,
    get: Callable | None = None,
    *,
    given: Collection[str] | None = None,
    node: str = '',
):
    """Build ``cls`` from the private parameters; ``defaults`` replaces field defaults known only at run time.

    :param get: ``get(name, default)``, :func:`rospy.get_param` unless given (tests pass a dict's).
    :param given: the names set on this node's command line; a wrong value of any other name is
        said to come from the parameter server (:func:`origin_note`). Under rospy (no ``get``),
        read from ``sys.argv``; otherwise None means every value counts as given.
    :param node: the node's resolved name, e.g. ``/world_sim`` (under rospy, its name).
    :raises ParamError: naming every parameter that is missing, of the wrong type or out of its range.
    """
    if get is None:
        import rospy

        get = rospy.get_param
        given = command_line_params() if given is None else given
        node = node or rospy.get_name()
    values, errors, from_server = {}, [], set()
    for field in dataclasses.fields(cls):
        value = get('~' + field.name, _MISSING)
        if value is not _MISSING:
            if given is not None and field.name not in given:
                from_server.add(field.name)
            try:  # the range too, so that one message lists every problem
                values[field.name] = checked(field, _joined(field, value))
            except ParamError as error:
                errors.append(error)
            continue
        default = (defaults or {}).get(field.name, field.default)
        if default is dataclasses.MISSING:
            errors.append(
                ParamError(field.name, f'required, not given (add _{field.name}:=VALUE to the command line)')
            )
            continue
        values[field.name] = default

    def note(name: str) -> str:
        return origin_note(node, name) if name in from_server else ''

    if errors:
        raise ParamError.combined(errors).annotated(note)
    try:
        return cls(**values)
    except ParamError as error:
        raise error.annotated(note) from None


def private_param_names(node: str, names: Iterable[str]) -> set[str]:
    """The private parameters of ``node`` among the server's ``names`` (``/node/a/b`` counts as ``a``)."""
    prefix = node.rstrip('/') + '/'
    return {name[len(prefix) :].split('/', 1)[0] for name in names if name.startswith(prefix)}


def unknown_param_warnings(
    cls, names: Iterable[str], given: Collection[str] | None = None, node: str = ''
) -> list[str]:
    """One warning for each private parameter in ``names`` that ``cls`` does not declare.

    >>> from drvs.server.params import ServerSettings
    >>> unknown_param_warnings(ServerSettings, ['forward_timout', 'lease'])
    ['unknown parameter ~forward_timout (ignored): did you mean ~forward_timeout?']
    """
    known = [field.name for field in dataclasses.fields(cls)]
    warnings = []
    for name in sorted(set(names) - set(known)):
        origin = origin_note(node, name) if given is not None and name not in given else ''
        close = difflib.get_close_matches(name, known, n=1)
        hint = f'did you mean ~{close[0]}?' if close else 'this node has no such parameter'
        warnings.append(f'unknown parameter ~{name} (ignored){origin}: {hint}')
    return warnings


def writable_folder(name: str, path: str) -> Path:
    """The folder ``path`` of the parameter ``~name``, created if needed and checked to be writable.

    :raises ParamError: ``~out: cannot write to the folder /x: Permission denied``.
    """
    folder = Path(path)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as error:
        raise ParamError(name, f'cannot write to the folder {path}: {error.strerror}') from None
    return folder
