"""Where the CLIs print their tables."""

from __future__ import annotations

from rich.console import Console


def table_console(*, stderr: bool = False, width: int = 170) -> Console:
    """A rich Console for tables. Off a terminal (a log file, CI output, a pipe) rich would wrap at
    80 columns and cut run names to '…', so it gets `width` columns there instead."""
    console = Console(stderr=stderr)
    return console if console.is_terminal else Console(stderr=stderr, width=width)
