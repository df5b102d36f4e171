"""The one exception root of ERNI and its subclasses, named after the state that is wrong."""

from __future__ import annotations


class ErniError(Exception):
    """Root of every error ERNI raises on purpose."""


class ConfigError(ErniError):
    """A configuration file or setting is invalid: `FILE: field.path: message`."""


class TaskError(ErniError, ValueError):
    """A task is invalid: `goto: missing 'x'`."""


class TransactionError(ErniError):
    """The blackboard was used outside a transaction, or an object is unknown or duplicated."""


class PluginError(ErniError):
    """A plugin could not be found, loaded or configured."""
