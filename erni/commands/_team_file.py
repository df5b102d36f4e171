"""How the commands find a team `erni sim` runs for the same user, without `--via`.

While its team is up, `erni sim` names it in a file of this user's runtime directory
(`$XDG_RUNTIME_DIR/erni/sim-PID.json`, else `erni-UID/` in the temporary directory; the directory
0700, the file 0600): the control node's address, the beacon port, the run's `cli` identity. It
removes the file when it stops. `erni task`, `peers`, `watch`, `record` and `console` given no
`--via`, `--zenoh` or `--discovery-port` reach the newest such team whose `erni sim` still runs,
when they were given no credentials of their own (no identity, no team key) or the run's identity.
"""

from __future__ import annotations

import json
import os
import stat
import tempfile
from pathlib import Path
from typing import Any

PREFIX = "sim-"  # RUNTIME/sim-PID.json


def runtime_dir() -> Path:
    """This user's directory for what a running `erni sim` tells the other commands."""
    base = os.environ.get("XDG_RUNTIME_DIR")
    if base and Path(base).is_dir():
        return Path(base) / "erni"
    return Path(tempfile.gettempdir()) / f"erni-{os.getuid()}"


def _private(path: Path) -> bool:
    """Whether `path` is this user's and no one else may write it (nor, for a file, read it)."""
    try:
        st = path.lstat()
    except OSError:
        return False
    mask = 0o077 if stat.S_ISREG(st.st_mode) else 0o022
    return st.st_uid == os.getuid() and not stat.S_ISLNK(st.st_mode) and not st.st_mode & mask


def announce(via: tuple[str, int], discovery_port: int, identity: str | Path, run_dir: str | Path) -> Path | None:
    """Name a running team in this user's runtime directory; return the file (None where it cannot be written)."""
    folder = runtime_dir()
    try:
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
        if not _private(folder):
            return None  # someone else's, or open to others: tell no one through it
        path = folder / f"{PREFIX}{os.getpid()}.json"
        temp = folder / f".{path.name}.tmp"
        fd = os.open(temp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump({"pid": os.getpid(), "started": started(os.getpid()), "via": f"{via[0]}:{via[1]}", "discovery_port": discovery_port,
                       "identity": str(identity), "run_dir": str(run_dir)}, f)
        os.replace(temp, path)
        return path
    except OSError:
        return None


def withdraw(path: Path | None) -> None:
    """Remove a team's file (quietly, when it is gone already)."""
    if path is not None:
        try:
            path.unlink()
        except OSError:
            pass


def running_sim() -> dict[str, Any] | None:
    """The newest team named in this user's runtime directory whose `erni sim` still runs, or None.
    Files of runs that no longer run (killed) are removed."""
    folder = runtime_dir()
    if not _private(folder):
        return None
    found: list[tuple[float, dict[str, Any]]] = []
    for path in folder.glob(f"{PREFIX}*.json"):
        try:
            if not _private(path):
                continue
            team = json.loads(path.read_text(encoding="utf-8"))
            pid, when = int(team["pid"]), path.stat().st_mtime
            str(team["via"]), str(team["identity"])
        except (OSError, ValueError, KeyError, TypeError):
            continue
        if _runs(pid, str(team.get("started", ""))):
            found.append((when, team))
        else:
            withdraw(path)
    return max(found, key=lambda f: f[0])[1] if found else None


def started(pid: int) -> str:
    """When process `pid` started (clock ticks after boot, from /proc), or '' where it cannot be told."""
    try:
        stat_line = Path(f"/proc/{pid}/stat").read_text(encoding="ascii", errors="replace")
        return stat_line.rsplit(")", 1)[1].split()[19]  # field 22, after the command name in parentheses
    except (OSError, IndexError):
        return ""


def _runs(pid: int, since: str) -> bool:
    """Whether the process that wrote a team's file still runs (one that took its PID since does not count)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, ValueError):
        return False  # not this user's: not a run of this user's erni sim
    now = started(pid)
    return not (since and now) or now == since
