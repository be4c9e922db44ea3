"""Safe YAML loading that remembers where every value came from (file and line).

Every mapping is loaded as a :class:`LocDict` and every sequence as a :class:`LocList`; both
carry the source file and the line of each key / item so that validation errors can say
"procedures/24pos.yaml:12: ...". Only ``yaml.SafeLoader`` is used: no arbitrary objects.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from .errors import InputError, InputErrors

__all__ = ["InputError", "InputErrors", "LocDict", "LocList", "load_file", "load_file_text", "load_text"]


class LocDict(dict):
    """A dict that knows its source file, its own line and the line of each key."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.file: str = "<string>"
        self.line: int = 0
        self.key_lines: dict = {}

    def line_of(self, key: Any) -> int:
        return self.key_lines.get(key, self.line)


class LocList(list):
    """A list that knows its source file, its own line and the line of each item."""

    def __init__(self, *args: Any) -> None:
        super().__init__(*args)
        self.file: str = "<string>"
        self.line: int = 0
        self.item_lines: list = []

    def line_of(self, index: int) -> int:
        return self.item_lines[index] if 0 <= index < len(self.item_lines) else self.line


class _LocLoader(yaml.SafeLoader):
    """The safe loader, building :class:`LocDict` / :class:`LocList` that name ``rigctl_file`` (set
    on each loader: one class for every file, not a class made per load)."""

    rigctl_file = "<string>"


def _construct_mapping(loader: _LocLoader, node: yaml.MappingNode) -> LocDict:
    file = loader.rigctl_file
    loader.flatten_mapping(node)
    out = LocDict()
    out.file, out.line, out.key_lines = file, node.start_mark.line + 1, {}
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node, deep=True)
        if not isinstance(key, (str, int, float, bool)) and key is not None:
            raise InputError("mapping keys must be plain scalars", file,
                             key_node.start_mark.line + 1)
        if key in out:
            raise InputError(f"duplicate key {key!r}", file, key_node.start_mark.line + 1,
                             "remove one of the two")
        out[key] = loader.construct_object(value_node, deep=True)
        out.key_lines[key] = key_node.start_mark.line + 1
    return out


def _construct_sequence(loader: _LocLoader, node: yaml.SequenceNode) -> LocList:
    out = LocList(loader.construct_object(child, deep=True) for child in node.value)
    out.file, out.line = loader.rigctl_file, node.start_mark.line + 1
    out.item_lines = [child.start_mark.line + 1 for child in node.value]
    return out


_LocLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)
_LocLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_SEQUENCE_TAG, _construct_sequence)


def load_text(text: str, file: str | Path = "<string>") -> Any:
    """Parse YAML text with the safe loader, keeping line numbers; errors name file and line."""
    try:
        loader = _LocLoader(text)  # (what yaml.load(text, Loader=...) does, with the file named)
        try:
            loader.rigctl_file = str(file)
            return loader.get_single_data()
        finally:
            loader.dispose()
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = mark.line + 1 if mark is not None else None
        raise InputError(f"YAML syntax error: {exc.problem or exc.context}", file, line,
                         "check indentation and quoting on that line") from None
    except yaml.YAMLError as exc:
        raise InputError(f"YAML error: {exc}", file) from None


def load_file(path: str | Path) -> Any:
    """Read and parse a YAML file (safe loader, line numbers kept)."""
    return load_file_text(path)[0]


def load_file_text(path: str | Path) -> tuple[Any, str]:
    """:func:`load_file`'s data and the text it was parsed from (read once)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError("file not found", p, hint="check the path") from None
    except IsADirectoryError:
        raise InputError("is a directory, expected a YAML file", p) from None
    except UnicodeDecodeError:
        raise InputError("not a UTF-8 text file", p) from None
    except OSError as exc:
        raise InputError(f"cannot read: {exc.strerror}", p) from None
    return load_text(text, p), text
