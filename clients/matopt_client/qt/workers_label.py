"""The daemon's renderer workers in the status bar: a one-line summary, each worker on hover.

A job that stalls because its worker is restarting (or could not start) looks, from the job
alone, like a slow job; the summary makes the cause visible at a glance, and the tooltip
gives each worker's details in the same words as ``matopt info``.
"""

from __future__ import annotations

import html
from PySide6.QtWidgets import QLabel, QWidget

from matopt_client import workers as wk
from matopt_api.v1 import matopt_pb2 as pb

TROUBLE_COLOR = "#9a4a00"  # the banner's warning tone, darker: readable on any status bar
TROUBLE_STYLE = f"QLabel {{ color: {TROUBLE_COLOR}; font-weight: bold; }}"


def _nobr(text: str) -> str:
    return f"<nobr>{html.escape(text)}</nobr>"


def tooltip_html(info: pb.ServerInfo) -> str:
    """The summary, then each worker with the CLI's cells, a short paragraph per worker.

    Not the CLI's space-aligned columns: a tooltip uses a proportional font, where spaces do
    not line columns up, and wraps rich text at about 80 characters, where seven columns
    fold into a tall, narrow mess. Each line here stays short; only the exit reason wraps.
    """
    blocks = [f"<p>{html.escape(wk.summary(info.workers))}</p>"]
    for worker in info.workers:
        name, state, device, process, memory, jobs, restarts = \
            wk.worker_cells(worker, info.variant)
        state = html.escape(state)
        if worker.state in wk.TROUBLE_STATES:
            state = f"<b style='color:{TROUBLE_COLOR}'>{state}</b>"
        head = f"<b>{html.escape(name)}</b> {state}"
        lines = [head, " · ".join(_nobr(c) for c in (device, process) if c),
                 " · ".join(_nobr(c) for c in (memory, jobs) if c)]
        if restarts:
            lines.append(html.escape(restarts))
        blocks.append(f"<p>{'<br>'.join(line for line in lines if line)}</p>")
    return "".join(blocks)


class WorkersLabel(QLabel):
    """``2 workers: 1 busy, 1 idle``; hidden while nothing is known about the workers (not
    connected, connection lost, or a daemon older than the workers list), so it never shows
    stale states."""

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.hide()

    def set_info(self, info: pb.ServerInfo | None) -> None:
        """Shows the workers of ``info``; None (no current answer from the daemon) hides them."""
        if info is None or not info.workers:
            self.setText("")
            self.setToolTip("")
            self.hide()
            return
        self.setText(wk.summary(info.workers))
        self.setToolTip(tooltip_html(info))
        self.setStyleSheet(TROUBLE_STYLE if wk.in_trouble(info.workers) else "")
        self.show()
