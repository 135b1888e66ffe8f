"""The daemon's log: text lines for a terminal, or one JSON object a line (``--log-format
json``) for a collector (journald's JSON export, Loki, Elasticsearch) that would otherwise
have to parse the text.

A JSON line has ``time`` (UTC, ISO 8601), ``level``, ``logger`` and ``message``, ``job`` and
``user`` where the line is about a job or a user's call (the caller sets them with
``extra=about(...)``), and ``exception`` with the traceback where there is one.
"""

from __future__ import annotations

import datetime
import json
import logging
import sys
import threading
from typing import BinaryIO

TEXT_FORMAT = "%(asctime)s %(name)s %(levelname)s %(message)s"
FIELDS = ("job", "user")  # what a record may carry besides its message


def about(job: str | None = None, user: str | None = None) -> dict[str, str]:
    """``extra=`` for a log call about a job and/or a user."""
    return {k: v for k, v in (("job", job), ("user", user)) if v}


class JsonFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        line = {"time": datetime.datetime.fromtimestamp(record.created, datetime.timezone.utc)
                .isoformat(timespec="milliseconds"),
                "level": record.levelname, "logger": record.name,
                "message": record.getMessage()}
        line.update({k: str(getattr(record, k)) for k in FIELDS if getattr(record, k, None)})
        if record.exc_info:
            line["exception"] = self.formatException(record.exc_info)
        elif record.exc_text:
            line["exception"] = record.exc_text
        return json.dumps(line, ensure_ascii=False)


_json = False


def as_json() -> bool:
    """Whether the log is JSON: then a worker's own output comes through ``relay``."""
    return _json


def relay(stream: BinaryIO, logger: str) -> None:
    """Logs each line of a worker process's stderr (Dr.Jit's warnings, a traceback) as a
    WARNING of ``logger``, from a thread of its own, until the process closes it: in a JSON
    log even what the renderer prints is one object a line."""
    def run() -> None:
        log = logging.getLogger(logger)
        with stream:
            for line in stream:
                log.warning("%s", line.decode(errors="replace").rstrip())
    threading.Thread(target=run, name=f"relay-{logger}", daemon=True).start()


def configure(level: str, form: str = "text") -> None:
    """The root logger, to stderr, at ``level`` in ``form`` ("text" or "json")."""
    global _json
    _json = form == "json"
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JsonFormatter() if form == "json" else logging.Formatter(TEXT_FORMAT))
    logging.basicConfig(level=level.upper(), handlers=[handler], force=True)
