"""Bounded input and honest output: every file misdirect reads or writes goes through here.

Hostile or merely extreme input must end in one clear line, never in a hang, a crash or a
success message for work that was not done (issue 15). So input files are checked with
``os.stat`` before they are opened (only regular files, at most :func:`max_file_bytes`), YAML
is composed by a loader that bounds nesting depth and alias expansion and refuses duplicate
keys, and every output is written to a temporary file beside the target and moved into place
with ``os.replace`` only once it is complete.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import stat
import tempfile
import unicodedata
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml
from yaml.constructor import ConstructorError, SafeConstructor
from yaml.events import (
    AliasEvent,
    MappingEndEvent,
    MappingStartEvent,
    ScalarEvent,
    SequenceEndEvent,
    SequenceStartEvent,
    StreamEndEvent,
)
from yaml.nodes import MappingNode, ScalarNode, SequenceNode
from yaml.resolver import Resolver

from misdirect.core.memory import check_memory as check_memory  # re-exported: it lived here
from misdirect.errors import ProblemError, WriteError

try:  # libyaml's scanner and parser; the composition below is ours either way
    from yaml._yaml import CParser as _EventSource
except ImportError:  # pragma: no cover - PyYAML built without libyaml
    from yaml.parser import Parser
    from yaml.reader import Reader
    from yaml.scanner import Scanner

    class _EventSource(Reader, Scanner, Parser):  # type: ignore[no-redef]
        def __init__(self, stream: str) -> None:
            Reader.__init__(self, stream)
            Scanner.__init__(self)
            Parser.__init__(self)


MAX_FILE_BYTES_ENV = "MISDIRECT_MAX_FILE_BYTES"
DEFAULT_MAX_FILE_BYTES = 256 * 1024**2
MAX_DEPTH = 64  # a problem file nests 5 levels; 64 leaves room and stays far from any stack
MAX_ALIAS_NODES = 100_000  # nodes YAML aliases may add beyond what the file itself spells out


def max_file_bytes() -> int:
    """The size limit for files read, from ``MISDIRECT_MAX_FILE_BYTES`` (default 256 MiB)."""
    text = os.environ.get(MAX_FILE_BYTES_ENV)
    if text is None:
        return DEFAULT_MAX_FILE_BYTES
    try:
        value = int(text)
    except ValueError:
        raise ProblemError(
            f"expected a number of bytes, got {text!r}", source=MAX_FILE_BYTES_ENV
        ) from None
    if value < 1:
        raise ProblemError(f"must be at least 1, got {value}", source=MAX_FILE_BYTES_ENV)
    return value


# -- one-line messages --------------------------------------------------------------------------

_BREAKING = ("Cc", "Cf", "Zl", "Zp")  # controls, invisible formatting, line/paragraph breaks


def one_line(text: str) -> str:
    """``text`` with control, formatting and line-breaking characters escaped as Python's
    ``repr`` writes them, so a name from a file can never split (or forge) a line of output."""
    if text.isprintable():
        return text
    return "".join(repr(c)[1:-1] if unicodedata.category(c) in _BREAKING else c for c in text)


# -- reading ------------------------------------------------------------------------------------


def _kind(mode: int) -> str:
    if stat.S_ISDIR(mode):
        return "a directory"
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def check_input_file(path: Path, *, source: str | None = None, field: str | None = None) -> int:
    """Size of ``path`` after checking it is a regular file within the size limit.

    Uses ``os.stat`` only, so a FIFO nobody writes to is refused without being opened."""
    where = {"source": source if source is not None else str(path), "field": field}
    try:
        info = os.stat(path)
    except FileNotFoundError:
        raise ProblemError("file not found", **where) from None
    except OSError as error:
        raise ProblemError(f"cannot read file ({error.strerror})", **where) from None
    if not stat.S_ISREG(info.st_mode):
        raise ProblemError(f"is {_kind(info.st_mode)}, not a regular file", **where)
    limit = max_file_bytes()
    if info.st_size > limit:
        raise ProblemError(
            f"file is {info.st_size:,} bytes, larger than the limit of {limit:,} bytes "
            f"(raise it with {MAX_FILE_BYTES_ENV})",
            **where,
        )
    return info.st_size


def read_text_file(path: Path, *, source: str | None = None, field: str | None = None) -> str:
    """The UTF-8 text of a regular file of at most :func:`max_file_bytes` bytes."""
    where = {"source": source if source is not None else str(path), "field": field}
    check_input_file(path, source=source, field=field)
    limit = max_file_bytes()
    try:
        # O_NONBLOCK: should the file have been swapped for a FIFO since the stat, do not wait
        descriptor = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
        with os.fdopen(descriptor, "rb") as handle:
            if not stat.S_ISREG(os.fstat(handle.fileno()).st_mode):
                raise ProblemError("is not a regular file", **where)
            data = handle.read(limit + 1)
    except OSError as error:
        raise ProblemError(f"cannot read file ({error.strerror})", **where) from None
    if len(data) > limit:
        raise ProblemError(
            f"file is larger than the limit of {limit:,} bytes (raise it with "
            f"{MAX_FILE_BYTES_ENV})",
            **where,
        )
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as error:
        line = data.count(b"\n", 0, error.start) + 1
        raise ProblemError(
            f"not UTF-8 text (byte {data[error.start]:#04x} at offset {error.start})",
            source=where["source"],
            field=f"line {line}",
        ) from None


# -- YAML ---------------------------------------------------------------------------------------


# types-PyYAML gives libyaml's events a yaml._yaml.Mark, a class apart from the yaml.error.Mark
# that nodes and errors are typed to take, though either does at runtime; and it types
# CParser.get_event Optional, though an event is pending wherever it is called here: hence
# the ignores [arg-type] and [union-attr] below.
class BoundedSafeLoader(_EventSource, SafeConstructor, Resolver):
    """``yaml.safe_load`` with limits: libyaml parses, and composition (ours, iterative, so
    deep nesting cannot overflow the C stack) bounds the depth at :data:`MAX_DEPTH` and the
    nodes aliases add at :data:`MAX_ALIAS_NODES` (a "billion laughs" stops at once); mapping
    construction refuses duplicate keys, naming both lines. Only safe tags are constructed."""

    def __init__(self, stream: str) -> None:
        _EventSource.__init__(self, stream)
        SafeConstructor.__init__(self)
        Resolver.__init__(self)
        self.anchors: dict[str, Any] = {}
        self.anchor_sizes: dict[str, int] = {}
        self.nodes = 0  # expanded size of everything composed so far
        self.alias_nodes = 0

    def plain_document(self) -> Any:
        """The document, built straight from the parser's events (no nodes, no constructor
        pass: a generated model loads several times faster, docs/benchmarks.md), for the
        documents problem files are: no anchors, aliases, explicit tags or merge keys, and
        only scalars as keys. On anything else it raises :class:`_NotPlainError`, and the caller
        parses the text again the general way (:meth:`get_single_data`). What it builds is
        what that builds: scalars by the same resolver and constructors, plain keys YAML
        would read as numbers, booleans, null or dates as the text written, duplicate keys
        and nesting past :data:`MAX_DEPTH` refused the same way."""
        get_event, resolve, constructors = self.get_event, self.resolve, self.yaml_constructors
        get_event()  # StreamStart
        if self.check_event(StreamEndEvent):
            return None
        get_event()  # DocumentStart
        # per open collection: [the collection, its pending key and line, each key's line]
        stack: list[list[Any]] = []
        while True:
            event: Any = get_event()  # typed as possibly None: one is pending throughout
            kind = type(event)
            if kind is ScalarEvent:
                tag = event.tag
                if event.anchor is not None or tag not in (None, "!"):
                    raise _NotPlainError
                tag = resolve(ScalarNode, event.value, event.implicit)
                as_key = bool(stack) and stack[-1][1] is None and type(stack[-1][0]) is dict
                if tag == _STR or (as_key and not event.style and tag in _TEXT_TAGS):
                    value = event.value
                elif as_key or tag not in constructors or tag == _MERGE:
                    raise _NotPlainError  # a key of another kind, or a merge: the general way
                else:
                    node = ScalarNode(tag, event.value, event.start_mark, event.end_mark)
                    value = constructors[tag](self, node)
            elif kind is SequenceStartEvent or kind is MappingStartEvent:
                if event.anchor is not None or event.tag not in (None, "!"):
                    raise _NotPlainError
                if len(stack) >= MAX_DEPTH:
                    raise _LimitError(f"nested deeper than {MAX_DEPTH} levels", event.start_mark)
                stack.append([[] if kind is SequenceStartEvent else {}, None, {}])
                continue
            elif kind is SequenceEndEvent or kind is MappingEndEvent:
                value = stack.pop()[0]
            else:  # an alias
                raise _NotPlainError
            if not stack:
                break
            collection, pending, lines = stack[-1]
            if type(collection) is list:
                collection.append(value)
            elif pending is None:
                if type(value) is list or type(value) is dict:
                    raise _NotPlainError  # a collection as a key
                stack[-1][1] = (value, event.start_mark.line + 1)
            else:
                key, line = pending
                if key in lines:
                    raise _DuplicateError(key, lines[key], line)
                lines[key] = line
                collection[key] = value
                stack[-1][1] = None
        get_event()  # DocumentEnd
        self._end_of_stream()
        return value

    # the Composer interface BaseConstructor.get_single_data uses
    def get_single_node(self) -> Any:
        self.get_event()  # StreamStart
        document = None
        if not self.check_event(StreamEndEvent):
            self.get_event()  # DocumentStart
            document = self._compose()
            self.get_event()  # DocumentEnd
            self.anchors, self.anchor_sizes = {}, {}
        self._end_of_stream()
        return document

    def _end_of_stream(self) -> None:
        """Consume the end of the stream, refusing a second document."""
        if not self.check_event(StreamEndEvent):
            event = self.get_event()
            raise yaml.composer.ComposerError(
                None,
                None,
                "expected one document, found another",
                event.start_mark,  # type: ignore[union-attr,arg-type]
            )
        self.get_event()

    def _compose(self) -> Any:
        # stack entries: [node, anchor, nodes before it, pending mapping key]
        stack: list[list[Any]] = []
        while True:
            event = self.get_event()
            if isinstance(event, AliasEvent):
                if event.anchor not in self.anchors:
                    raise yaml.composer.ComposerError(
                        None,
                        None,
                        f"found undefined alias {event.anchor!r}",
                        event.start_mark,  # type: ignore[arg-type]
                    )
                node = self.anchors[event.anchor]
                size = self.anchor_sizes[event.anchor]
                self.nodes += size
                self.alias_nodes += size
                if self.alias_nodes > MAX_ALIAS_NODES:
                    raise _LimitError(
                        f"YAML aliases expand to more than {MAX_ALIAS_NODES:,} nodes "
                        "(an alias bomb?)",
                        event.start_mark,
                    )
            elif isinstance(event, ScalarEvent):
                tag = event.tag
                if tag is None or tag == "!":
                    tag = self.resolve(ScalarNode, event.value, event.implicit)
                node = ScalarNode(
                    tag,
                    event.value,
                    event.start_mark,  # type: ignore[arg-type]
                    event.end_mark,  # type: ignore[arg-type]
                    style=event.style,
                )
                self.nodes += 1
                self._anchor(event, node, self.nodes - 1)
            elif isinstance(event, SequenceStartEvent | MappingStartEvent):
                if len(stack) >= MAX_DEPTH:
                    raise _LimitError(f"nested deeper than {MAX_DEPTH} levels", event.start_mark)
                kind = SequenceNode if isinstance(event, SequenceStartEvent) else MappingNode
                tag = event.tag
                if tag is None or tag == "!":
                    tag = self.resolve(kind, None, event.implicit)
                node = kind(tag, [], event.start_mark, None, flow_style=event.flow_style)  # type: ignore[arg-type]
                stack.append([node, event.anchor, self.nodes, None])
                self.nodes += 1
                if event.anchor is not None:
                    self._check_anchor(event)
                    self.anchors[event.anchor] = node
                continue
            elif isinstance(event, SequenceEndEvent | MappingEndEvent):
                node, anchor, before, _ = stack.pop()
                node.end_mark = event.end_mark
                if anchor is not None:
                    self.anchor_sizes[anchor] = self.nodes - before
            else:  # pragma: no cover - the parser guarantees the order of events
                raise yaml.composer.ComposerError(
                    None,
                    None,
                    f"unexpected {type(event).__name__}",
                    event.start_mark,  # type: ignore[union-attr,arg-type]
                )
            if not stack:
                return node
            parent = stack[-1]
            if isinstance(parent[0], SequenceNode):
                parent[0].value.append(node)
            elif parent[3] is None:
                parent[3] = (node,)
            else:
                parent[0].value.append((parent[3][0], node))
                parent[3] = None

    def _check_anchor(self, event: Any) -> None:
        if event.anchor in self.anchors:
            raise yaml.composer.ComposerError(
                f"found duplicate anchor {event.anchor!r}; first occurrence",
                self.anchors[event.anchor].start_mark,
                "second occurrence",
                event.start_mark,
            )

    def _anchor(self, event: Any, node: Any, before: int) -> None:
        if event.anchor is not None:
            self._check_anchor(event)
            self.anchors[event.anchor] = node
            self.anchor_sizes[event.anchor] = self.nodes - before

    def construct_written_int(self, node: Any) -> int:
        """An integer, remembering how it was written when that is not how Python writes it
        (``010``, YAML 1.1's octal 8): a name written so is read as written."""
        try:
            value = SafeConstructor.construct_yaml_int(self, node)
        except ValueError:  # more digits than Python converts (4,300)
            raise ConstructorError(
                None, None, f"a number of {len(node.value):,} digits is too long", node.start_mark
            ) from None
        return WrittenInt(value, node.value) if node.value != str(value) else value

    def construct_mapping(self, node: Any, deep: bool = False) -> dict[Any, Any]:
        if isinstance(node, MappingNode):
            # keys are names or field names: text as written (``010`` stays "010", ``1`` is
            # "1", so that 1 and "1" are one key, reported twice), never YAML's numbers
            node.value = [(_as_text(key_node), value_node) for key_node, value_node in node.value]
            seen: dict[Any, int] = {}
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue  # keys a merge brings in may be overridden, as YAML intends
                key = self.construct_object(key_node, deep=True)
                line = key_node.start_mark.line + 1
                try:
                    if key in seen:
                        raise _DuplicateError(key, seen[key], line)
                    seen[key] = line
                except TypeError:
                    continue  # an unhashable key: BaseConstructor reports it
        return super().construct_mapping(node, deep=deep)


# types-PyYAML types add_constructor for loaders, not for a constructor class of our own
BoundedSafeLoader.add_constructor(  # type: ignore[type-var]
    "tag:yaml.org,2002:int", BoundedSafeLoader.construct_written_int
)

_TEXT_TAGS = {f"tag:yaml.org,2002:{kind}" for kind in ("int", "float", "bool", "null", "timestamp")}
_STR, _MERGE = "tag:yaml.org,2002:str", "tag:yaml.org,2002:merge"


class _NotPlainError(Exception):
    """A document :meth:`BoundedSafeLoader.plain_document` leaves to the general way."""


class WrittenInt(int):
    """A YAML integer with the text it was written as (``010``), for names."""

    written: str

    def __new__(cls, value: int, written: str) -> WrittenInt:
        number = super().__new__(cls, value)
        number.written = written
        return number


def _as_text(node: Any) -> Any:
    """A plain scalar key that YAML would read as a number, a boolean, null or a date, as the
    text it was written."""
    if isinstance(node, ScalarNode) and not node.style and node.tag in _TEXT_TAGS:
        return ScalarNode(
            "tag:yaml.org,2002:str", node.value, node.start_mark, node.end_mark, style=None
        )
    return node


class _LimitError(yaml.YAMLError):
    def __init__(self, reason: str, mark: Any):
        super().__init__(reason)
        self.reason, self.mark = reason, mark


class _DuplicateError(yaml.YAMLError):
    def __init__(self, key: Any, first: int, second: int):
        super().__init__(f"duplicate key {key!r}")
        self.key, self.first, self.second = key, first, second


def _where(mark: Any) -> str | None:
    return f"line {mark.line + 1}, column {mark.column + 1}" if mark is not None else None


_SURROGATE_ESCAPE = re.compile(r"\\(?:u|U0000)[dD][89a-fA-F]")


def check_text(document: Any, text: str, *, source: str) -> Any:
    """``document`` (parsed from ``text``), refused if an escape (``\\ud800``) made a lone
    surrogate of one of its strings: that is no text, and could not be printed or written."""
    if _SURROGATE_ESCAPE.search(text) is None:  # only escapes make them: UTF-8 cannot
        return document
    pending: list[tuple[Any, str]] = [(document, "")]
    while pending:
        value, where = pending.pop()
        items: Any = ()
        if isinstance(value, dict):
            items = [(f"{where}.{key}", key) for key in value] + [
                (f"{where}.{key}", item) for key, item in value.items()
            ]
        elif isinstance(value, list):
            items = [(f"{where}[{i}]", item) for i, item in enumerate(value)]
        elif isinstance(value, str):
            try:
                value.encode("utf-8")
            except UnicodeEncodeError as error:
                bad = value[error.start]
                raise ProblemError(
                    f"{bad!r} is a lone surrogate, not text (write the character itself)",
                    source=source,
                    field=where.lstrip(".") or None,
                ) from None
        pending.extend((item, path) for path, item in items)
    return document


def parse_yaml(text: str, *, source: str) -> Any:
    """The document in ``text``, or a one-line ProblemError naming ``source`` and the line."""
    loader = BoundedSafeLoader(text)
    try:
        try:
            document = loader.plain_document()
        except _NotPlainError:  # anchors, tags, merge keys: parsed again, the general way
            loader.dispose()
            loader = BoundedSafeLoader(text)
            document = loader.get_single_data()
        return check_text(document, text, source=source)
    except _DuplicateError as error:
        raise ProblemError(
            f"duplicate key {error.key!r} (first at line {error.first}); a second value would "
            "silently replace the first",
            source=source,
            field=f"line {error.second}",
        ) from None
    except _LimitError as error:
        raise ProblemError(
            f"invalid YAML: {error.reason}", source=source, field=_where(error.mark)
        ) from None
    except ConstructorError as error:
        mark = error.problem_mark
        raise ProblemError(
            f"invalid YAML: {error.problem or error}", source=source, field=_where(mark)
        ) from None
    except yaml.YAMLError as error:
        mark = getattr(error, "problem_mark", None)
        reason = getattr(error, "problem", None) or str(error)
        if "maximum nesting depth" in reason:  # PyYAML 6.0.4 stops at its own, deeper limit
            reason = f"nested deeper than {MAX_DEPTH} levels"
        raise ProblemError(f"invalid YAML: {reason}", source=source, field=_where(mark)) from None
    except RecursionError:  # pragma: no cover - the depth limit comes first
        raise ProblemError(
            f"invalid YAML: nested deeper than {MAX_DEPTH} levels", source=source
        ) from None
    finally:
        loader.dispose()


# -- JSON ---------------------------------------------------------------------------------------


class _DuplicateKeyError(ValueError):
    def __init__(self, key: str):
        super().__init__(key)
        self.key = key


def _pairs(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    document = dict(pairs)
    if len(document) != len(pairs):
        seen: set[str] = set()
        for key, _ in pairs:
            if key in seen:
                raise _DuplicateKeyError(key)
            seen.add(key)
    return document


_JSON_TOKEN = re.compile(r'"(?:[^"\\]|\\.)*"\s*:?|[{}\[\]]', re.DOTALL)


def _duplicate_lines(text: str, key: str) -> tuple[int, int] | None:
    """Lines of the first repeated key of one object (only on the error path: a Python scan)."""
    stack: list[dict[str, int] | None] = []
    for match in _JSON_TOKEN.finditer(text):
        token = match.group()
        if token in "{[":
            stack.append({} if token == "{" else None)
        elif token in "}]":
            if stack:
                stack.pop()
        elif token.endswith(":") and stack and stack[-1] is not None:
            name = json.loads(token[:-1].rstrip())
            line = text.count("\n", 0, match.start()) + 1
            if name in stack[-1]:
                if name == key:
                    return stack[-1][name], line
            else:
                stack[-1][name] = line
    return None


def _depth(document: Any) -> int:
    """Nesting depth of lists and dicts, without recursion."""
    deepest = 0
    pending = [(document, 1)]
    while pending:
        value, depth = pending.pop()
        if isinstance(value, dict):
            value = list(value.values())
        elif not isinstance(value, list):
            continue
        deepest = max(deepest, depth)
        if depth <= MAX_DEPTH:
            pending.extend((item, depth + 1) for item in value if isinstance(item, list | dict))
    return deepest


def parse_json(text: str, *, source: str) -> Any:
    """The document in ``text``; duplicate keys, deep nesting and syntax errors are one-line
    ProblemsError naming ``source`` and the line."""
    try:
        document = json.loads(text, object_pairs_hook=_pairs)
    except _DuplicateKeyError as error:
        lines = _duplicate_lines(text, error.key)
        first, field = (f" (first at line {lines[0]})", f"line {lines[1]}") if lines else ("", None)
        raise ProblemError(
            f"duplicate key {error.key!r}{first}; a second value would silently replace the first",
            source=source,
            field=field,
        ) from None
    except json.JSONDecodeError as error:
        raise ProblemError(
            f"invalid JSON: {error.msg}",
            source=source,
            field=f"line {error.lineno}, column {error.colno}",
        ) from None
    except RecursionError:
        raise ProblemError(
            f"invalid JSON: nested deeper than {MAX_DEPTH} levels", source=source
        ) from None
    except ValueError:  # an integer of more digits than Python converts (4,300)
        long = re.search(r"\d{4000,}", text)
        line = f"line {text.count(chr(10), 0, long.start()) + 1}" if long else None
        raise ProblemError(
            "invalid JSON: a number is too long", source=source, field=line
        ) from None
    if _depth(document) > MAX_DEPTH:
        raise ProblemError(f"invalid JSON: nested deeper than {MAX_DEPTH} levels", source=source)
    return check_text(document, text, source=source)


# -- writing ------------------------------------------------------------------------------------

_BAD_PATH = {errno.ENOENT, errno.ENOTDIR, errno.EISDIR, errno.EACCES, errno.EPERM, errno.EROFS}


def check_output_path(path: Path, *, field: str = "path") -> None:
    """Refuse, before any work, an output path that cannot be written: a missing folder, a
    folder in its place, a parent that is not a folder (ProblemError, exit code 2). ``field``:
    what the error names (the caller's parameter; the CLI passes or maps its flag)."""
    path = Path(path)
    if str(path) == "" or path.name in ("", ".", ".."):
        raise ProblemError(f"cannot write {str(path)!r}: not a file name", field=field)
    parent = path.parent
    try:
        info = os.stat(path)
    except FileNotFoundError:
        info = None
    except OSError as error:
        raise ProblemError(f"cannot write {path}: {error.strerror}", field=field) from None
    if info is not None and stat.S_ISDIR(info.st_mode):
        raise ProblemError(f"cannot write {path}: it is a directory", field=field)
    if info is None:
        try:
            parent_info = os.stat(parent)
        except FileNotFoundError:
            raise ProblemError(
                f"cannot write {path}: directory {parent} does not exist", field=field
            ) from None
        except OSError as error:
            raise ProblemError(f"cannot write {path}: {error.strerror}", field=field) from None
        if not stat.S_ISDIR(parent_info.st_mode):
            raise ProblemError(f"cannot write {path}: {parent} is not a directory", field=field)


def _fail_write(path: Path, error: OSError, field: str) -> Exception:
    reason = error.strerror or str(error)
    if error.errno in _BAD_PATH:
        return ProblemError(f"cannot write {path}: {reason}", field=field)
    return WriteError(f"cannot write {path}: {reason}")


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_output(
    path: Path,
    content: str | bytes | Callable[[Path], None],
    *,
    field: str = "path",
) -> Path:
    """Write ``content`` (text, bytes, or a function that writes the file it is given) to
    ``path`` atomically: into a temporary file in the same folder (same suffix, so writers that
    go by it still work), checked to exist, then moved over ``path``. A device or FIFO that
    already exists (``/dev/null``, ``/dev/full``, a pipe) is written in place. A bad path is a
    ProblemError (exit code 2); a failing write (disk full, I/O error) a WriteError (exit 1)."""
    path = Path(path)
    check_output_path(path, field=field)
    data = content.encode("utf-8") if isinstance(content, str) else content
    try:
        info = os.stat(path)
    except OSError:
        info = None
    if info is not None and not stat.S_ISREG(info.st_mode):  # a device or a pipe
        if callable(data):  # the writer wants a file: let it write one, then copy it over
            with tempfile.TemporaryDirectory() as folder:
                staged = Path(folder) / f"output{path.suffix}"
                data(staged)
                if not staged.is_file():
                    raise WriteError(f"cannot write {path}: the writer produced no file")
                data = staged.read_bytes()
        try:
            with open(path, "wb") as handle:
                handle.write(data)
        except OSError as error:
            raise _fail_write(path, error, field) from None
        return path
    target = Path(os.path.realpath(path))  # replace the file a symlink points to, not the link
    try:
        descriptor, name = tempfile.mkstemp(
            dir=target.parent, prefix=f".{target.stem}.", suffix=target.suffix
        )
    except OSError as error:
        raise _fail_write(path, error, field) from None
    temporary = Path(name)
    try:
        try:
            if callable(data):
                os.close(descriptor)
                data(temporary)
                if not temporary.is_file() or (temporary.stat().st_size == 0):
                    raise WriteError(f"cannot write {path}: the writer produced no file")
            else:
                with os.fdopen(descriptor, "wb") as handle:
                    handle.write(data)
                    handle.flush()
                    os.fsync(handle.fileno())
            mode = stat.S_IMODE(info.st_mode) if info is not None else 0o666 & ~_umask()
            os.chmod(temporary, mode)
            os.replace(temporary, target)
        except OSError as error:
            raise _fail_write(path, error, field) from None
    except BaseException:
        with contextlib.suppress(OSError):
            temporary.unlink()
        raise
    return path


def prepare_output_dir(path: Path, *, field: str = "path") -> None:
    """Create the output folder (and its parents), or refuse at once with one line."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise ProblemError(
            f"cannot use {path}: it exists and is not a directory", field=field
        ) from None
    except OSError as error:
        raise ProblemError(f"cannot create {path}: {error.strerror}", field=field) from None
    if not os.access(path, os.W_OK):
        raise ProblemError(f"cannot write into {path}: permission denied", field=field)
