"""Copying a process image into a snapshot slot cheaply (runtime/shared/shm.py publishes).

Owns: the byte runs of a slot that are contiguous in a ProcessImage's buffer too (%QX %MX are
adjacent in both layouts, so are %QW %MW, %QD %MD and %QL %ML: eight copies instead of
twelve), as memoryview pairs bound once per image buffer: a slice assignment between
memoryviews is a plain memcpy, about 4x cheaper than np.copyto for these few KB (issue 15.5).
Does not know: the segment's header, its seqlock, the status record.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from softplc.core.image import ImageSizes, image_offsets

# (area, start, stop) byte offsets of the six areas in a slot (shm.py's layout)
SlotLayout = Sequence[tuple[str, int, int, object]]
_RUNS = (("ix", "ix"), ("qx", "mx"), ("iw", "iw"), ("qw", "mw"), ("id", "id"), ("qd", "md"),
         ("il", "il"), ("ql", "ml"))


class SlotCopies:
    """Per slot, the runs to copy from an image buffer; rebound when the buffer changes."""

    def __init__(self, segment: npt.NDArray[np.uint8], slots: Sequence[int], sizes: ImageSizes,
                 layout: SlotLayout) -> None:
        offsets = image_offsets(sizes)
        area = {name: (start, stop) for name, start, stop, _ in layout}
        self._runs: list[list[tuple[npt.NDArray[np.uint8], int, int]]] = []
        for at in slots:
            runs = []
            for first, last in _RUNS:
                lo, hi = offsets[first][0], offsets[last][1]
                start, stop = at + area[first][0], at + area[last][1]
                assert stop - start == hi - lo, "slot and image layouts disagree"
                runs.append((segment[start:stop], lo, hi))
            self._runs.append(runs)
        self._source: npt.NDArray[np.uint8] | None = None  # the image buffer bound
        self._copies: list[list[tuple[memoryview, memoryview]]] = []

    def copy(self, slot: int, source: npt.NDArray[np.uint8]) -> None:
        """Copy the image buffer `source` into slot `slot`."""
        if source is not self._source:
            self.release()
            self._copies = [[(target.data, source[lo:hi].data) for target, lo, hi in runs]
                            for runs in self._runs]
            self._source = source
        for into, run in self._copies[slot]:
            into[:] = run

    def release(self) -> None:
        """Let go of the views (the segment cannot be unmapped while they exist)."""
        for runs in self._copies:
            for into, run in runs:
                into.release()
                run.release()
        self._copies = []
        self._source = None

    def close(self) -> None:
        self.release()
        self._runs = []
