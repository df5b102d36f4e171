"""`python -m erni` is the same as the `erni` command."""

from erni.cli import main

raise SystemExit(main())
