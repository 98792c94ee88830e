"""YAML loading that remembers where every value came from, for errors that name file:line."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from dcuscope.core.errors import ConfigError

KeyPath = tuple  # of str (mapping keys) and int (sequence indexes)


def format_path(path: KeyPath) -> str:
    """``("stages", 1, "infer", "threshold")`` -> ``stages[1].infer.threshold``."""
    out = ""
    for part in path:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "(top level)"


@dataclass(frozen=True)
class Document:
    """A parsed YAML file: plain Python data plus the line of every key path."""

    file: Path
    data: Any
    lines: dict[KeyPath, int]

    def line(self, path: KeyPath) -> int:
        """Line of ``path``, or of its nearest ancestor that has one."""
        while path not in self.lines and path:
            path = path[:-1]
        return self.lines.get(path, 1)

    def error(self, path: KeyPath, message: str) -> ConfigError:
        return ConfigError(f"{self.file}:{self.line(path)}: {format_path(path)}: {message}")


def load_document(file: Path) -> Document:
    """Parse ``file``; a missing file or malformed YAML raises one-line ConfigError."""
    try:
        text = file.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{file}: no such configuration file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{file}: cannot read: {exc}") from exc
    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{file}:{mark.line + 1}" if mark is not None else str(file)
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ConfigError(f"{where}: malformed YAML: {problem}") from exc
    lines: dict[KeyPath, int] = {}
    data = _convert(node, (), lines, file) if node is not None else None
    return Document(file, data, lines)


def _convert(node: yaml.Node, path: KeyPath, lines: dict[KeyPath, int], file: Path) -> Any:
    lines[path] = node.start_mark.line + 1
    if isinstance(node, yaml.MappingNode):
        out = {}
        for key_node, value_node in node.value:
            key = _scalar(key_node, file)
            if not isinstance(key, str):
                raise ConfigError(f"{file}:{key_node.start_mark.line + 1}: {format_path(path)}: keys must be text, got {key!r}")
            if key in out:
                raise ConfigError(f"{file}:{key_node.start_mark.line + 1}: {format_path(path + (key,))}: duplicate key")
            out[key] = _convert(value_node, path + (key,), lines, file)
            lines[path + (key,)] = key_node.start_mark.line + 1
        return out
    if isinstance(node, yaml.SequenceNode):
        return [_convert(item, path + (i,), lines, file) for i, item in enumerate(node.value)]
    return _scalar(node, file)


def _scalar(node: yaml.Node, file: Path) -> Any:
    if not isinstance(node, yaml.ScalarNode):
        raise ConfigError(f"{file}:{node.start_mark.line + 1}: keys must be plain text")
    return yaml.SafeLoader("").construct_object(node)
