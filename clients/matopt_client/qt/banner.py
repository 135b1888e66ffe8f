"""A message strip across the top of the window, for what the user must not miss.

Errors go here rather than into modal dialogs: a modal box would stop the window (and every
live update behind it) until dismissed, and a lost connection or a refused job is a state to
see and act on, not a question to answer. The strip stays until the cause is gone (the
connection is back) or the user closes it.
"""

from __future__ import annotations

from PySide6.QtCore import Qt
from PySide6.QtWidgets import QFrame, QHBoxLayout, QLabel, QToolButton, QWidget

STYLES = {
    "error": "background: #fde2e1; color: #7a1212; border: 1px solid #e7a3a0;",
    "warning": "background: #fff4d6; color: #6b4b00; border: 1px solid #e8cf86;",
    "info": "background: #e3effc; color: #0d3c6e; border: 1px solid #a9c8ec;",
}


class Banner(QFrame):
    """One message with a severity ("error", "warning", "info") and a close button."""

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        layout = QHBoxLayout(self)
        layout.setContentsMargins(8, 4, 4, 4)
        self.label = QLabel("")
        self.label.setWordWrap(True)
        self.label.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        close = QToolButton()
        close.setText("✕")
        close.setAutoRaise(True)
        close.setToolTip("dismiss")
        close.clicked.connect(self.clear)
        layout.addWidget(self.label, 1)
        layout.addWidget(close)
        self.level = ""
        self.hide()

    def show_message(self, text: str, level: str = "error") -> None:
        self.level = level
        self.setStyleSheet(f"Banner {{ {STYLES.get(level, STYLES['error'])} }}"
                           f" QLabel {{ border: none; background: transparent; }}")
        self.label.setText(text)
        self.show()

    def clear(self) -> None:
        self.level = ""
        self.label.setText("")
        self.hide()

    def text(self) -> str:
        return self.label.text() if self.level else ""
