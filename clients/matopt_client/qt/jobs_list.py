"""The user's jobs on the server, whoever started them: this window, the CLI or a script.

The daemon, not the window, owns jobs; a job started with ``matopt job start`` on another
machine is just as much the user's, so the list comes from ListJobs (refreshed periodically)
and any row can be opened to watch it, see its results or edit and restart it.
"""

from __future__ import annotations

from datetime import datetime
from typing import Sequence

from PySide6.QtCore import Signal
from PySide6.QtGui import QFont
from PySide6.QtWidgets import (QAbstractItemView, QHBoxLayout, QLabel, QPushButton,
                               QTableWidget, QTableWidgetItem, QVBoxLayout, QWidget)

from matopt_client import client as mc
from matopt_client import workflow
from matopt_api.v1 import matopt_pb2 as pb

COLUMNS = ["Job", "State", "Iteration", "Best loss", "Created"]


def short_id(name: str) -> str:
    return name.rsplit("/", 1)[-1]


def created(job: pb.Job) -> str:
    if not job.HasField("create_time"):
        return ""
    return datetime.fromtimestamp(job.create_time.seconds).strftime("%Y-%m-%d %H:%M")


class JobsList(QWidget):
    """A table of jobs, newest first; ``open_requested(name)`` on double-click or Open."""

    open_requested = Signal(str)
    refresh_requested = Signal()

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        layout = QVBoxLayout(self)
        layout.setContentsMargins(4, 4, 4, 4)
        self.table = QTableWidget(0, len(COLUMNS))
        self.table.setHorizontalHeaderLabels(COLUMNS)
        self.table.verticalHeader().setVisible(False)
        self.table.setSelectionBehavior(QAbstractItemView.SelectionBehavior.SelectRows)
        self.table.setSelectionMode(QAbstractItemView.SelectionMode.SingleSelection)
        self.table.setEditTriggers(QAbstractItemView.EditTrigger.NoEditTriggers)
        # Sized to the contents once per fill (set_jobs), not on every cell change: with
        # ResizeToContents each change measures the whole column.
        self.table.horizontalHeader().setStretchLastSection(True)
        self.table.cellDoubleClicked.connect(lambda row, _: self._open_row(row))
        layout.addWidget(self.table)
        row = QHBoxLayout()
        self.open_button = QPushButton("Open")
        self.open_button.setToolTip("watch this job, see its results, or edit and restart it")
        self.open_button.clicked.connect(lambda: self._open_row(self.table.currentRow()))
        self.refresh_button = QPushButton("Refresh")
        self.refresh_button.clicked.connect(self.refresh_requested)
        self.note = QLabel("")
        row.addWidget(self.open_button)
        row.addWidget(self.refresh_button)
        row.addWidget(self.note, 1)
        layout.addLayout(row)
        self.jobs: list[pb.Job] = []
        self.current: str | None = None

    def set_jobs(self, jobs: Sequence[pb.Job]) -> None:
        """Replaces the rows, keeping the selected job selected.

        Called on every refresh and every watched job's event (several a second while a job
        runs), so cells are rewritten only where their text changed and the columns are sized
        once per fill: a rebuild per event stalled the window once the daemon held many jobs.
        """
        selected = self.selected_name()
        self.jobs = sorted(jobs, key=lambda j: (j.create_time.seconds, j.create_time.nanos),
                           reverse=True)
        grew = self.table.rowCount() != len(self.jobs)
        self.table.setUpdatesEnabled(False)
        try:
            self.table.setRowCount(len(self.jobs))
            for i, job in enumerate(self.jobs):
                self._fill_row(i, job)
                if job.name == selected and self.table.currentRow() != i:
                    self.table.selectRow(i)
            if grew:
                self.table.resizeColumnsToContents()
        finally:
            self.table.setUpdatesEnabled(True)
        self.note.setText(f"{len(self.jobs)} job{'s' if len(self.jobs) != 1 else ''}")

    def _fill_row(self, i: int, job: pb.Job) -> None:
        total = job.spec.iterations if job.spec.HasField("iterations") else 0
        best = workflow.best(job)
        cells = [short_id(job.name), mc.state_name(job.state),
                 f"{job.iteration}/{total}" if total else str(job.iteration),
                 f"{best[1]:.4g}" if best else "", created(job)]
        tip = f"{job.name}\nscene {job.spec.scene}"
        if job.iteration:
            tip += f"\nlast loss {job.loss:.4g}"
        if job.error:
            tip += f"\n{job.error}"
        bold = job.name == self.current
        for column, text in enumerate(cells):
            item = self.table.item(i, column)
            if item is None:
                item = QTableWidgetItem(text)
                self.table.setItem(i, column, item)
            elif item.text() != text:
                item.setText(text)
            if item.toolTip() != tip:
                item.setToolTip(tip)
            if item.font().bold() != bold:
                font = QFont(item.font())
                font.setBold(bold)
                item.setFont(font)

    def update_job(self, job: pb.Job) -> None:
        """A newer state of a listed job (from its watch stream), without waiting for the next
        ListJobs: its row alone."""
        for i, old in enumerate(self.jobs):
            if old.name == job.name:
                self.jobs[i] = job
                self._fill_row(i, job)
                return

    def set_current(self, name: str | None) -> None:
        """Marks the job the window shows (bold)."""
        previous, self.current = self.current, name
        for i, job in enumerate(self.jobs):
            if job.name in (previous, name):
                self._fill_row(i, job)

    def names(self) -> list[str]:
        return [j.name for j in self.jobs]

    def selected_name(self) -> str | None:
        row = self.table.currentRow()
        return self.jobs[row].name if 0 <= row < len(self.jobs) else None

    def select(self, name: str) -> None:
        for i, job in enumerate(self.jobs):
            if job.name == name:
                self.table.selectRow(i)
                return

    def _open_row(self, row: int) -> None:
        if 0 <= row < len(self.jobs):
            self.open_requested.emit(self.jobs[row].name)
