"""The control node's UI: web GUI, speech and typed command grammar, spoken feedback."""

from erni.plugins.ui.dialogue import Dialogue, Naming, Reply, tasks_for
from erni.plugins.ui.grammar import Command, Refusal, parse, vocabulary
from erni.plugins.ui.plugin import UIPlugin, UISettings

__all__ = ["Command", "Dialogue", "Naming", "Refusal", "Reply", "UIPlugin", "UISettings", "parse",
           "tasks_for", "vocabulary"]
