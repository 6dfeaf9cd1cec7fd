"""The firing engine (docs/design.md section 3): one firing round of a compiled net.

Owns: the public names, Engine (engine.py), Step, the interleaving API for analysis and the
bounds a round keeps. Does not know: YAML, devices, HMI, wall-clock time.
"""

from softplc.core.engine.bindings import MAX_BINDINGS
from softplc.core.engine.counts import SMALL_NET
from softplc.core.engine.diagnostics import MAX_DIAGNOSTICS
from softplc.core.engine.engine import Engine, enabled_transitions, fire_one
from softplc.core.engine.step import Step

__all__ = ["MAX_BINDINGS", "MAX_DIAGNOSTICS", "SMALL_NET", "Engine", "Step", "enabled_transitions",
           "fire_one"]
