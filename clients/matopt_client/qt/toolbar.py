"""The window's toolbar: connect, open a scene (with its XML defaults), load references,
start, pause, resume, cancel, export. Each action calls the window's method of the same
purpose, which tests and scripts call directly."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from PySide6.QtGui import QAction, QKeySequence
from PySide6.QtWidgets import QLabel, QLineEdit, QMainWindow


@dataclass
class Actions:
    """The toolbar's actions (enabled and disabled by the window) and its overrides field."""

    connect: QAction
    open: QAction
    cornell: QAction
    references: QAction
    start: QAction
    pause: QAction
    resume: QAction
    cancel: QAction
    export: QAction
    overrides: QLineEdit


def add_toolbar(window: QMainWindow, overrides_text: str) -> Actions:
    """Adds the toolbar to ``window`` (a MainWindow), its actions wired to its methods."""
    toolbar = window.addToolBar("Main")
    toolbar.setObjectName("main-toolbar")
    toolbar.setMovable(False)

    def action(text: str, slot: Callable, shortcut: str | None = None,
               tip: str = "") -> QAction:
        a = QAction(text, window)
        a.triggered.connect(slot)
        if shortcut:
            a.setShortcut(QKeySequence(shortcut))
        if tip:
            a.setToolTip(tip)
        toolbar.addAction(a)
        return a

    connect = action("Connect…", window.connect_dialog, tip="server, token and TLS CA of matoptd")
    toolbar.addSeparator()
    open_ = action("Open scene…", window.open_scene_dialog, "Ctrl+O",
                   "upload a Mitsuba scene XML and every file it references")
    cornell = action("Cornell box", lambda: window.open_cornell_box(),
                     tip="the daemon's built-in test scene")
    overrides = QLineEdit(overrides_text)
    overrides.setPlaceholderText("XML defaults, e.g. resx=64 resy=64")
    overrides.setToolTip("<default> values a scene is loaded with (as the CLI's --set); "
                         "applied when a scene is opened")
    overrides.setMaximumWidth(220)
    toolbar.addWidget(QLabel(" with "))
    toolbar.addWidget(overrides)
    references = action("Load references…", window.choose_references, "Ctrl+R",
                        "one reference image per sensor")
    toolbar.addSeparator()
    start = action("Start", window.start_job, "Ctrl+Return",
                   "start a job with the setup on the left (a job opened from the list: "
                   "restart it with your edits)")
    pause = action("Pause", window.pause_job)
    resume = action("Resume", window.resume_job)
    cancel = action("Cancel", window.cancel_job)
    toolbar.addSeparator()
    export = action("Export…", window.export_dialog, "Ctrl+E",
                    "write the shown result to a folder")
    return Actions(connect, open_, cornell, references, start, pause, resume, cancel, export,
                   overrides)
