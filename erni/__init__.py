"""ERNI command-line entry points and launch helpers."""

__version__ = "0.1.0"
