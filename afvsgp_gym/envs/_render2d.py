"""Tiny numpy rasteriser for the point-mass environment (no display or OpenGL needed)."""

from __future__ import annotations

import numpy as np


class Canvas:
    """Square RGB image of a world window ``[-extent, extent]^2`` (first two coordinates)."""

    def __init__(self, size: int = 256, extent: float = 1.0) -> None:
        self.size = size
        self.extent = extent
        self.img = np.full((size, size, 3), 255, dtype=np.uint8)
        ij = np.arange(size, dtype=np.float64)
        scale = 2.0 * extent / size
        self._x = (ij + 0.5) * scale - extent  # column -> x
        self._y = extent - (ij + 0.5) * scale  # row -> y (up)

    def disc(self, center, radius: float, color, filled: bool = True) -> None:
        """Draw a disc (or a ring 2 px wide when ``filled`` is False)."""
        dx = self._x[None, :] - float(center[0])
        dy = self._y[:, None] - float(center[1])
        r = np.sqrt(dx * dx + dy * dy)
        if filled:
            mask = r <= radius
        else:
            px = 2.0 * self.extent / self.size
            mask = np.abs(r - radius) <= px
        self.img[mask] = color
