"""TOML files handed to the operator (agent configs, scenarios, worlds, floor plans), read within bounds.

A file someone else wrote may be built to hurt the reader: nested thousands of levels deep (the
parser recurses once a level, and its traceback runs to thousands of lines), an integer of
100,000 digits (Python refuses to convert it, with a traceback), a key of 100,000 dotted parts
(the parser's time grows with the square of the parts). Before it is parsed, a file is held to:

| bound | default | what |
|---|---|---|
| `MAX_BYTES` | 1 MiB | the file's size |
| `MAX_DEPTH` | 32 | tables within tables: a header's and a dotted key's parts, arrays and inline tables, counted together |
| `MAX_NUMBER` | 64 characters | one number or date literal |
| integers | 64 bits | -2^63 .. 2^63 - 1, as TOML defines them |

A file outside them is refused with one line that names the file, the line and the bound
(`robot.toml:5: nested deeper than 32 levels (tables, dotted keys, arrays); expected at most 32`);
nothing else is read from it. The scan before the parser takes time in proportion to the file.
"""

from __future__ import annotations

import re
import tomllib
from pathlib import Path
from typing import Any

from erni.blackboard.errors import ConfigError

MAX_BYTES = 1024 * 1024
MAX_DEPTH = 32
MAX_NUMBER = 64
INT_MIN, INT_MAX = -(2**63), 2**63 - 1

_NEXT = re.compile(r"""[#"'\[\]{},=\n]|[A-Za-z0-9_+\-.:]+""")
_BASIC_REST = re.compile(r'(?:[^"\\\n]|\\.)*"')  # after the opening quote, through the closing one
_MULTI_BASIC_REST = re.compile(r'(?:[^"\\]|\\.|"(?!""))*"""', re.S)


def read_text(path: Path, what: str, error: type[ConfigError] = ConfigError) -> str:
    """The text of a TOML file no larger than `MAX_BYTES` (checked before it is read), or `error`
    naming the file and what was expected."""
    try:
        size = path.stat().st_size
        if size > MAX_BYTES and path.is_file():
            raise error(f"{path}: {size} bytes; expected a {what} file of at most {MAX_BYTES} bytes")
        with path.open("rb") as f:
            data = f.read(MAX_BYTES + 1)
    except FileNotFoundError:
        raise error(f"{path}: no such {what} file") from None
    except IsADirectoryError:
        raise error(f"{path}: is a directory; expected a {what} TOML file") from None
    except OSError as err:
        raise error(f"{path}: cannot read: {err.strerror or err}") from None
    if len(data) > MAX_BYTES:  # a file that grew, a device
        raise error(f"{path}: more than {MAX_BYTES} bytes; expected a {what} file of at most {MAX_BYTES} bytes")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        raise error(f"{path}: not UTF-8 text; expected a {what} TOML file") from None


def loads(text: str, source: str, error: type[ConfigError] = ConfigError) -> dict[str, Any]:
    """Parse TOML text held to the bounds above; raise `error` (`SOURCE[:LINE]: what is wrong`)."""
    size = len(text.encode("utf-8", "surrogatepass"))
    if size > MAX_BYTES:
        raise error(f"{source}: {size} bytes; expected at most {MAX_BYTES}")
    problem = _scan(text)
    if problem:
        raise error(f"{source}:{problem}")
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise error(f"{source}: not valid TOML: {err}") from None
    except (RecursionError, ValueError) as err:  # what the scan cannot see coming (it should not happen)
        raise error(f"{source}: not readable TOML: {str(err).splitlines()[0][:120]}") from None
    problem = _too_large_integer(data)
    if problem:
        raise error(f"{source}: {problem}")
    return data


def _scan(text: str) -> str:
    """`LINE: problem` for the first bound the text breaks (depth, a number's length), '' if none.

    A small lexer: strings and comments are skipped whole, a table header's and a key's parts are
    counted (dots outside quotes), arrays and inline tables are a stack. Unterminated strings end
    the scan: the parser then names them."""
    line = 1
    table = 0  # the parts of the table header in force
    stack: list[str] = []  # open arrays ('[') and inline tables ('{') of the value being read
    saved: list[int] = []  # for each of them, the parts of the key it is the value of
    key_parts = 0  # the dotted parts of the key being read (0: no key yet)
    expect_key = True  # at a line's start outside any value, or after '{' or ',' in an inline table
    i, end = 0, len(text)
    while i < end:
        m = _NEXT.search(text, i)
        if m is None:
            break
        token, i = m.group(), m.end()
        head = token[0]
        if head == "\n":
            line += 1
            if not stack:
                expect_key, key_parts = True, 0
        elif head == "#":
            nl = text.find("\n", i)
            i = end if nl < 0 else nl
        elif head == '"':
            if text.startswith('""', i):
                rest = _MULTI_BASIC_REST.match(text, i + 2)
                if rest is None:
                    break
                line += text.count("\n", i, rest.end())
                i = rest.end()
            else:
                rest = _BASIC_REST.match(text, i)
                if rest is None:
                    break
                i = rest.end()
            if expect_key:
                key_parts = max(key_parts, 1)
        elif head == "'":
            if text.startswith("''", i):
                close = text.find("'''", i + 2)
                if close < 0:
                    break
                line += text.count("\n", i, close)
                i = close + 3
            else:
                close = text.find("'", i)
                if close < 0 or "\n" in text[i:close]:
                    break
                i = close + 1
            if expect_key:
                key_parts = max(key_parts, 1)
        elif expect_key and head == "[" and not stack and key_parts == 0:  # a table header: [a.b] or [[a.b]]
            close = text.find("\n", i)
            header = text[i:end if close < 0 else close]
            parts = _header_parts(header)
            table = parts + 1 if header.startswith("[") else parts
            if table > MAX_DEPTH:
                return f"{line}: a table nested {table} levels deep; expected at most {MAX_DEPTH}"
            i = end if close < 0 else close
        elif expect_key and head not in "[]{},=":  # a key's part(s), or the dots between quoted parts
            key_parts = max(key_parts, 1) + token.count(".")
            depth = table + sum(saved) + key_parts + len(stack)
            if depth > MAX_DEPTH:
                return (f"{line}: a key nested {depth} levels deep (tables, dotted keys, arrays); expected at "
                        f"most {MAX_DEPTH}")
        elif head == "=":
            expect_key = False
        elif head in "[{":
            stack.append(head)
            saved.append(key_parts)
            key_parts = 0
            if table + sum(saved) + len(stack) > MAX_DEPTH:
                return (f"{line}: a value nested deeper than {MAX_DEPTH} levels (tables, dotted keys, arrays); "
                        f"expected at most {MAX_DEPTH}")
            expect_key = head == "{"
        elif head in "]}":
            if stack:
                stack.pop()
                key_parts = saved.pop()
            expect_key = False
        elif head == ",":
            if stack and stack[-1] == "{":
                expect_key, key_parts = True, 0
        elif (head.isdigit() or head in "+-") and len(token) > MAX_NUMBER:
            return f"{line}: a number of {len(token)} characters; expected at most {MAX_NUMBER} (a 64-bit integer, a float)"
    return ""


def _header_parts(header: str) -> int:
    """The dotted parts of a table header's text (after its first '['), quoted parts counted once."""
    parts, quote = 1, ""
    for ch in header:
        if quote:
            if ch == quote:
                quote = ""
        elif ch in "\"'":
            quote = ch
        elif ch == ".":
            parts += 1
        elif ch == "]":
            break
    return parts


def _too_large_integer(data: Any) -> str:
    """The first integer outside 64 bits in parsed TOML data ('' if none), walked without recursion."""
    stack = [data]
    while stack:
        item = stack.pop()
        if isinstance(item, dict):
            stack.extend(item.values())
        elif isinstance(item, list):
            stack.extend(item)
        elif isinstance(item, int) and not isinstance(item, bool) and not INT_MIN <= item <= INT_MAX:
            return f"integer {str(item)[:20]}... beyond 64 bits; expected -2^63 .. 2^63 - 1"
    return ""
