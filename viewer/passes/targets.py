"""Render targets that follow the frame size: created on the first size, re-created on a change."""

from __future__ import annotations


class SizedTargets:
    """Subclasses implement `create_targets(size)` and `release_targets()`."""

    size: tuple[int, int] = (0, 0)

    def resize(self, size: tuple[int, int]) -> None:
        if size == self.size:
            return
        if self.size != (0, 0):
            self.release_targets()
        self.size = size
        self.create_targets(size)

    def create_targets(self, size: tuple[int, int]) -> None:
        raise NotImplementedError

    def release_targets(self) -> None:
        raise NotImplementedError
