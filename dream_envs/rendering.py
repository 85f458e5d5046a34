"""OpenCV drawing shared by the grid environments: a readable top-down picture of a grid."""

from __future__ import annotations

from typing import Sequence, Tuple

import cv2
import numpy as np

Color = Tuple[int, int, int]

# RGB colours, chosen to stay distinguishable for colour-blind readers where possible.
COLORS: dict[str, Color] = {
    "background": (245, 245, 245),
    "grid": (200, 200, 200),
    "agent": (20, 20, 20),
    "text": (30, 30, 30),
    "gray": (140, 140, 140),
    "goal": (255, 215, 0),
    "red": (228, 26, 28),
    "blue": (55, 126, 184),
    "green": (77, 175, 74),
    "purple": (152, 78, 163),
    "orange": (255, 127, 0),
    "brown": (166, 86, 40),
    "pink": (247, 129, 191),
    "teal": (0, 150, 150),
}
# Colours for up to 7 distinct items (bus colours, ingredients).
PALETTE: list[Color] = [COLORS[c] for c in ("red", "blue", "green", "purple", "orange", "brown", "pink")]


class GridCanvas:
    """A top-down picture of a ``width`` x ``height`` grid; (0, 0) is drawn bottom-left, y grows upward.

    :param cell: size of one cell in pixels.
    :param margin: pixels of free space below the grid for a caption.
    """

    def __init__(self, width: int, height: int, cell: int = 48, caption_lines: int = 2) -> None:
        self.width, self.height, self.cell = width, height, cell
        self.caption_height = 22 * caption_lines
        self.image = np.full((height * cell + self.caption_height, width * cell, 3), COLORS["background"], np.uint8)
        for i in range(width + 1):
            cv2.line(self.image, (i * cell, 0), (i * cell, height * cell), COLORS["grid"], 1)
        for j in range(height + 1):
            cv2.line(self.image, (0, j * cell), (width * cell, j * cell), COLORS["grid"], 1)
        self._caption_row = 0

    def _corner(self, x: int, y: int) -> Tuple[int, int]:
        return x * self.cell, (self.height - 1 - y) * self.cell

    def center(self, x: int, y: int) -> Tuple[int, int]:
        px, py = self._corner(x, y)
        return px + self.cell // 2, py + self.cell // 2

    def fill(self, x: int, y: int, color: Color, inset: int = 2) -> None:
        px, py = self._corner(x, y)
        cv2.rectangle(self.image, (px + inset, py + inset), (px + self.cell - inset, py + self.cell - inset), color, -1)

    def square(self, x: int, y: int, color: Color, scale: float = 0.6, thickness: int = -1) -> None:
        cx, cy = self.center(x, y)
        h = int(self.cell * scale / 2)
        cv2.rectangle(self.image, (cx - h, cy - h), (cx + h, cy + h), color, thickness)

    def circle(self, x: int, y: int, color: Color, scale: float = 0.3, thickness: int = -1) -> None:
        cv2.circle(self.image, self.center(x, y), int(self.cell * scale), color, thickness, lineType=cv2.LINE_AA)

    def text(self, x: int, y: int, label: str, color: Color = COLORS["text"], scale: float = 0.45) -> None:
        (tw, th), _ = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
        cx, cy = self.center(x, y)
        cv2.putText(
            self.image, label, (cx - tw // 2, cy + th // 2), cv2.FONT_HERSHEY_SIMPLEX, scale, color, 1, cv2.LINE_AA
        )

    def agent(self, x: int, y: int) -> None:
        """The agent: a black triangle over its cell."""
        cx, cy = self.center(x, y)
        r = int(self.cell * 0.28)
        pts = np.array([[cx, cy - r], [cx - r, cy + r], [cx + r, cy + r]], np.int32)
        cv2.fillPoly(self.image, [pts], COLORS["agent"], lineType=cv2.LINE_AA)

    def arrow(self, src: Sequence[int], dst: Sequence[int], color: Color) -> None:
        cv2.arrowedLine(self.image, self.center(*src), self.center(*dst), color, 1, cv2.LINE_AA, tipLength=0.04)

    def caption(self, line: str) -> None:
        y = self.height * self.cell + 16 + 22 * self._caption_row
        cv2.putText(self.image, line, (6, y), cv2.FONT_HERSHEY_SIMPLEX, 0.45, COLORS["text"], 1, cv2.LINE_AA)
        self._caption_row += 1

    def frame(self) -> np.ndarray:
        return self.image.copy()
