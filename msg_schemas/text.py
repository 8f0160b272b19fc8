"""Text from messages and files made fit for one log or error line; no ROS needed, so the
commands and the nodes share it."""

from __future__ import annotations

LINE_LIMIT = 400  # characters of a message-supplied text in a log or error line


def one_line(text: object, limit: int = LINE_LIMIT) -> str:
    """Newlines folded, cut at `limit` characters (a 1 MB frame_id from a bad publisher is not
    logged whole on every message)."""
    line = " ".join(str(text).split())
    return line if len(line) <= limit else line[:limit - 3] + "..."
