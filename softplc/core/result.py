"""What one scan returns.

Owns: ScanResult, a frozen value: the image after the scan, the events, the transitions fired
and completed, the marking's changes and the replies to the commands it applied.
Does not know: how a scan is made (core/scan.py) or what keeps its results (core/plc.py).
"""

from __future__ import annotations

from dataclasses import dataclass

from softplc.core.image import ProcessImage
from softplc.core.snapshot import CommandReply


@dataclass(frozen=True, slots=True)
class ScanResult:
    outputs: ProcessImage  # the PLC's image after the scan (outputs and memory committed)
    events: tuple[str, ...]  # event conditions that occurred and events the program emitted
    fired: tuple[str, ...]
    completed: tuple[str, ...]
    marking_changes: dict[str, int]
    replies: tuple[CommandReply, ...]
    outputs_changed: bool = True  # False: the output image equals the previous scan's
