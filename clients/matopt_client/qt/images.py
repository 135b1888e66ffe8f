"""Showing renders: the daemon's 8-bit sRGB PNGs, fetched once and kept, shown via QPixmap.

Every image the daemon makes comes as a linear OpenEXR (for numbers) and an sRGB PNG (for
eyes); the app only ever shows the PNG, so it needs no HDR decoding. Blobs are named by their
SHA-256, so a downloaded one never changes and can be cached on disk across runs: switching
back and forth between sensors or best/last costs one download each, once.
"""

from __future__ import annotations

from pathlib import Path

from PySide6.QtCore import QSize, Qt
from PySide6.QtGui import QImage, QPixmap, QResizeEvent
from PySide6.QtWidgets import QFrame, QLabel, QSizePolicy, QVBoxLayout, QWidget

from matopt_client import client as mc


class BlobCache:
    """Content-addressed files under one folder; fetch() runs on a worker thread."""

    def __init__(self, directory: str | Path) -> None:
        self.directory = Path(directory)

    def path(self, blob: str) -> Path:
        return self.directory / blob.rsplit("/", 1)[-1]

    def fetch(self, client: mc.Client, blob: str) -> Path:
        """The blob's file, downloaded (and verified by download_blob) unless already here."""
        path = self.path(blob)
        if not path.is_file():
            mc.download_blob(client, blob, path)
        return path

    def image(self, client: mc.Client, blob: str) -> QImage:
        """The blob decoded; QImage (unlike QPixmap) may be made off the GUI thread."""
        return read_image(self.fetch(client, blob))


def read_image(path: str | Path) -> QImage:
    """A PNG/JPEG file as a QImage; a null QImage for formats Qt cannot read (OpenEXR)."""
    return QImage(str(path))


class ImagePane(QWidget):
    """A title, an image scaled to fit (small renders enlarged with visible pixels, as the
    32-64 px images of quick tests would otherwise be a blur), and a caption below."""

    def __init__(self, title: str, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        layout = QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        layout.setSpacing(2)
        self.title = QLabel(f"<b>{title}</b>")
        self.title.setAlignment(Qt.AlignmentFlag.AlignHCenter)
        self.view = QLabel()
        self.view.setAlignment(Qt.AlignmentFlag.AlignCenter)
        self.view.setFrameShape(QFrame.Shape.StyledPanel)
        self.view.setMinimumSize(120, 120)
        self.view.setSizePolicy(QSizePolicy.Policy.Expanding, QSizePolicy.Policy.Expanding)
        self.view.setStyleSheet("QLabel { background: #202020; color: #c8c8c8; }")
        self.view.setWordWrap(True)
        self.caption = QLabel("")
        self.caption.setAlignment(Qt.AlignmentFlag.AlignHCenter)
        self.caption.setWordWrap(True)
        layout.addWidget(self.title)
        layout.addWidget(self.view, 1)
        layout.addWidget(self.caption)
        self.image: QImage | None = None
        self.key: str | None = None  # what is shown (a blob or a path), to skip re-fetching
        self.set_placeholder("")

    def sizeHint(self) -> QSize:
        return QSize(240, 240)

    def set_image(self, image: QImage | None, caption: str, key: str | None = None,
                  placeholder: str = "cannot display this image") -> None:
        """Shows ``image``; a null or missing one shows ``placeholder`` instead."""
        if image is None or image.isNull():
            self.set_placeholder(placeholder, caption)
            return
        self.image, self.key = image, key
        self.caption.setText(caption)
        self._rescale()

    def set_placeholder(self, text: str, caption: str = "") -> None:
        self.image, self.key = None, None
        self.view.setPixmap(QPixmap())
        self.view.setText(text)
        self.caption.setText(caption)

    def has_image(self) -> bool:
        return self.image is not None

    def resizeEvent(self, event: QResizeEvent) -> None:  # noqa: N802 - Qt's name
        super().resizeEvent(event)
        self._rescale()

    def _rescale(self) -> None:
        if self.image is None:
            return
        pixmap = QPixmap.fromImage(self.image)
        size = self.view.contentsRect().size()
        if size.width() < 2 or size.height() < 2:
            size = QSize(max(self.image.width(), 1), max(self.image.height(), 1))
        enlarge = (pixmap.width() * 2 <= size.width() and pixmap.height() * 2 <= size.height())
        mode = (Qt.TransformationMode.FastTransformation if enlarge
                else Qt.TransformationMode.SmoothTransformation)
        self.view.setText("")
        self.view.setPixmap(pixmap.scaled(size, Qt.AspectRatioMode.KeepAspectRatio, mode))
