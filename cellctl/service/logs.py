"""The service's log: one line per record, whatever a client sent. Keys, scene paths and reasons come
from clients; a newline or a NUL in one must not forge a line of the cell's log (or of journald's), so
every record's message has its control and line-separator characters escaped before it is written."""

from __future__ import annotations

import logging
import re
import sys

# C0 and C1 controls, DEL, and Unicode's own line and paragraph separators
_UNSAFE = re.compile("[\x00-\x1f\x7f-\x9f\u2028\u2029]")


def escape(text: str) -> str:
    """``text`` on one line: each unsafe character as its Python escape (``\\n``, ``\\x00``, ``\\u2028``)."""
    return _UNSAFE.sub(lambda m: m.group().encode("unicode_escape").decode("ascii"), text)


class OneLine(logging.Filter):
    """Escapes the message (the traceback of ``log.exception`` is the service's own and stays as it is)."""

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        safe = escape(message)
        if safe != message or record.args:
            record.msg, record.args = safe, None
        return True


def setup(level: int = logging.INFO) -> None:
    """stderr, one escaped line per record (the service and its job worker)."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
    handler.addFilter(OneLine())
    logging.basicConfig(level=level, handlers=[handler])
