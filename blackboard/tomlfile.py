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
    return _Scanner(text).run()


def _skip_quoted(text: str, i: int, quote: str) -> tuple[int, int] | None:
    """Past the string whose opening `quote` ends at `i`: (where it ends, the newlines in it); None
    when it is not terminated."""
    if quote == '"':
        if text.startswith('""', i):
            rest = _MULTI_BASIC_REST.match(text, i + 2)
            return None if rest is None else (rest.end(), text.count("\n", i, rest.end()))
        rest = _BASIC_REST.match(text, i)
        return None if rest is None else (rest.end(), 0)
    if text.startswith("''", i):
        close = text.find("'''", i + 2)
        return None if close < 0 else (close + 3, text.count("\n", i, close))
    close = text.find("'", i)
    return None if close < 0 or "\n" in text[i:close] else (close + 1, 0)


class _Scanner:
    """`_scan`'s state: where it is, the table header in force, the key being read and the open values."""

    def __init__(self, text: str) -> None:
        self.text = text
        self.i, self.end = 0, len(text)
        self.line = 1
        self.table = 0  # the parts of the table header in force
        self.stack: list[str] = []  # open arrays ('[') and inline tables ('{') of the value being read
        self.saved: list[int] = []  # for each of them, the parts of the key it is the value of
        self.key_parts = 0  # the dotted parts of the key being read (0: no key yet)
        self.expect_key = True  # at a line's start outside any value, or after '{' or ',' in an inline table

    def run(self) -> str:
        while self.i < self.end:
            m = _NEXT.search(self.text, self.i)
            if m is None:
                break
            token, self.i = m.group(), m.end()
            problem = self._token(token)
            if problem is None:  # an unterminated string: the parser names it
                break
            if problem:
                return problem
        return ""

    def _token(self, token: str) -> str | None:
        """Take one token: '' when it breaks no bound, the problem when it does, None to end the scan."""
        head = token[0]
        if head == "\n":
            self.line += 1
            if not self.stack:
                self.expect_key, self.key_parts = True, 0
        elif head == "#":
            nl = self.text.find("\n", self.i)
            self.i = self.end if nl < 0 else nl
        elif head in "\"'":
            return self._string(head)
        elif self.expect_key and head == "[" and not self.stack and self.key_parts == 0:
            return self._header()
        elif self.expect_key and head not in "[]{},=":
            return self._key(token)
        elif head == "=":
            self.expect_key = False
        elif head in "[{":
            return self._open(head)
        elif head in "]},":
            self._close(head)
        elif (head.isdigit() or head in "+-") and len(token) > MAX_NUMBER:
            return (f"{self.line}: a number of {len(token)} characters; expected at most {MAX_NUMBER} "
                    "(a 64-bit integer, a float)")
        return ""

    def _string(self, quote: str) -> str | None:
        past = _skip_quoted(self.text, self.i, quote)
        if past is None:
            return None
        self.i, newlines = past
        self.line += newlines
        if self.expect_key:
            self.key_parts = max(self.key_parts, 1)
        return ""

    def _header(self) -> str:
        """A table header: [a.b] or [[a.b]]."""
        close = self.text.find("\n", self.i)
        header = self.text[self.i:self.end if close < 0 else close]
        parts = _header_parts(header)
        self.table = parts + 1 if header.startswith("[") else parts
        if self.table > MAX_DEPTH:
            return f"{self.line}: a table nested {self.table} levels deep; expected at most {MAX_DEPTH}"
        self.i = self.end if close < 0 else close
        return ""

    def _key(self, token: str) -> str:
        """A key's part(s), or the dots between quoted parts."""
        self.key_parts = max(self.key_parts, 1) + token.count(".")
        depth = self.table + sum(self.saved) + self.key_parts + len(self.stack)
        if depth > MAX_DEPTH:
            return (f"{self.line}: a key nested {depth} levels deep (tables, dotted keys, arrays); expected at "
                    f"most {MAX_DEPTH}")
        return ""

    def _close(self, head: str) -> None:
        """An array or an inline table closes, or a comma separates its items."""
        if head == ",":
            if self.stack and self.stack[-1] == "{":
                self.expect_key, self.key_parts = True, 0
            return
        if self.stack:
            self.stack.pop()
            self.key_parts = self.saved.pop()
        self.expect_key = False

    def _open(self, head: str) -> str:
        """An array or an inline table opens."""
        self.stack.append(head)
        self.saved.append(self.key_parts)
        self.key_parts = 0
        if self.table + sum(self.saved) + len(self.stack) > MAX_DEPTH:
            return (f"{self.line}: a value nested deeper than {MAX_DEPTH} levels (tables, dotted keys, arrays); "
                    f"expected at most {MAX_DEPTH}")
        self.expect_key = head == "{"
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
