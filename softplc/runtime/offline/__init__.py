"""Simulation and replay away from a live PLC (issue 40.5): `softplc simulate`'s runner
(simulate) and its script format (simscript), over the scan room's runner and trace.

May import the scan room; the scan room never imports it (tests/test_architecture.py
SUBROOMS), so the scan process does not load it.
"""
