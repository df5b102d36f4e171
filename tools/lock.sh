#!/usr/bin/env bash
# Refresh requirements.lock: the exact versions (with their hashes) of everything ERNI and its test
# suite install, resolved from pyproject.toml's ranges by uv for every platform and Python >= 3.11.
# The README's test command and .ci/run install from the lock; tests/test_lock.py checks that it
# still agrees with pyproject.toml. Run after changing a dependency, commit both files together.
#
#   tools/lock.sh                         keep every pin the ranges still allow; resolve only what changed
#   tools/lock.sh --upgrade               every package to the newest version its range allows
#   tools/lock.sh --upgrade-package NAME  only NAME (and what it needs) to its newest allowed version
set -euo pipefail
cd "$(dirname "$0")/.."
UV_VERSION=0.13.9
uv=$(command -v uv || true)
if [ -z "$uv" ] || [ "$("$uv" --version | cut -d' ' -f2)" != "$UV_VERSION" ]; then
    tooldir="${XDG_CACHE_HOME:-$HOME/.cache}/erni-lock-uv-$UV_VERSION"
    [ -x "$tooldir/bin/uv" ] || { python3 -m venv "$tooldir" && "$tooldir/bin/pip" install -q "uv==$UV_VERSION"; }
    uv="$tooldir/bin/uv"
fi
exec "$uv" pip compile pyproject.toml --extra test --universal --python-version 3.11 --fork-strategy fewest \
    --generate-hashes "$@" --custom-compile-command "tools/lock.sh" -o requirements.lock
