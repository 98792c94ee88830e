"""The ``--help`` layout of every ``dcuscope`` command: argparse's, wrapped to the terminal's width
(at most ``MAX_WIDTH`` columns when the output is no terminal), keeping the layout of texts written
by hand (paragraphs, indented examples and lists) and wrapping only what does not fit."""

from __future__ import annotations

import argparse
import re
import shutil
import sys
import textwrap

MAX_WIDTH = 100
"""Help written to a file or a pipe wraps here, whatever COLUMNS says."""
COMMAND = re.compile(r"dcuscope |gst-launch-1\.0 |python3? |[A-Z][A-Z_]*=")
"""An indented line starting so is a shell command: wrapped with a backslash, so it still runs."""
WORD = re.compile(r"""(?:"[^"]*"|'[^']*'|\S)+""")
"""A shell word, quoted parts kept whole."""


def use_everywhere(parser: argparse.ArgumentParser) -> None:
    """Make :class:`HelpFormatter` the formatter of ``parser`` and of all its subcommands, nested too."""
    parser.formatter_class = HelpFormatter
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                use_everywhere(sub)


def help_width() -> int:
    """The terminal's width, as argparse takes it; at most MAX_WIDTH when stdout is no terminal."""
    columns = shutil.get_terminal_size().columns
    return columns if sys.stdout.isatty() else min(columns, MAX_WIDTH)


class HelpFormatter(argparse.HelpFormatter):
    """argparse's formatter at :func:`help_width`, for hand-written descriptions and epilogs too."""

    def __init__(self, prog: str, indent_increment: int = 2, max_help_position: int = 24,
                 width: int | None = None) -> None:
        super().__init__(prog, indent_increment, max_help_position, width or help_width() - 2)

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        return "\n".join(indent + line for line in fill_raw(text, width - len(indent)))

    def _format_usage(self, usage, actions, groups, prefix) -> str:
        text = super()._format_usage(usage, actions, groups, prefix)
        if usage is None or max(map(len, text.splitlines())) <= self._width:
            return text  # argparse wrapped its own; a usage given by hand it never wraps
        head = (prefix or "usage: ") + self._prog
        body = text.strip()[len(head):]
        return "\n".join(_greedy(_top_level(" ".join(body.split())), self._width, head, " " * (len(head) + 1))) + "\n\n"


def fill_raw(text: str, width: int) -> list[str]:
    """``text``'s lines, each block (a paragraph, an indented item with its deeper continuation
    lines, a command with its ``\\`` continuations) kept as written where it fits in ``width``,
    refilled where a line of it does not."""
    out: list[str] = []
    for block in _blocks(text.strip("\n").splitlines()):
        if all(len(line) <= width for line in block):
            out += block
        elif _is_command(block[0]):
            out += _wrap_command(block, width)
        else:
            out += _wrap_prose(block, width)
    return out


def _indent(line: str) -> int:
    return len(line) - len(line.lstrip())


def _is_command(line: str) -> bool:
    return _indent(line) > 0 and COMMAND.match(line.lstrip()) is not None


def _blocks(lines: list[str]) -> list[list[str]]:
    blocks: list[list[str]] = []
    for line in lines:
        last = blocks[-1] if blocks else None
        if last is not None and line.strip() and last[-1].strip() and _continues(last, line):
            last.append(line)
        else:
            blocks.append([line])
    return blocks


def _continues(block: list[str], line: str) -> bool:
    """Whether ``line`` belongs to ``block``: the next line of a paragraph, of a command ending in a
    backslash, or deeper than the item it continues."""
    first = block[0]
    if _is_command(first):
        return block[-1].rstrip().endswith("\\")
    if _indent(first) == 0:
        return _indent(line) == 0
    return _indent(line) > _indent(first) and not _is_command(line)


def _wrap_prose(block: list[str], width: int) -> list[str]:
    first = block[0]
    lead = " " * _indent(first)
    if len(block) > 1:
        hang = " " * _indent(block[1])
    else:  # "  NAME    text": the text's column; else four deeper
        item = re.match(r"(\s*\S+(?: \S+)*\s{2,})\S", first)
        hang = " " * (len(item.group(1)) if item and _indent(first) else len(lead) + 4 * bool(lead))
    words = " ".join(line.strip() for line in block)
    return textwrap.wrap(words, width, initial_indent=lead, subsequent_indent=hang, break_long_words=False,
                         break_on_hyphens=False)


def _wrap_command(block: list[str], width: int) -> list[str]:
    lead = " " * _indent(block[0])
    words = WORD.findall(" ".join(line.strip().removesuffix("\\") for line in block))
    return _greedy(words, width - 2, lead, lead + "    ", " \\")


def _top_level(usage: str) -> list[str]:
    """``usage`` split at the spaces outside brackets: ``[--relay-cert FILE [--relay-key FILE]]`` stays one."""
    parts, depth, start = [], 0, 0
    for i, c in enumerate(usage):
        depth += (c in "[(") - (c in "])")
        if c == " " and depth == 0:
            parts.append(usage[start:i])
            start = i + 1
    parts.append(usage[start:])
    return [p for p in parts if p]


def _greedy(words: list[str], width: int, first: str, rest: str, end: str = "") -> list[str]:
    """``words`` in lines of at most ``width`` (a word longer stays whole), each but the last ending in ``end``."""
    lines, line = [], first
    for word in words:
        if line.strip() and len(line) + 1 + len(word) > width:
            lines.append(line.rstrip() + end)
            line = rest
        line += ("" if not line.strip() else " ") + word
    lines.append(line)
    return lines
