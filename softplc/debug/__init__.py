"""The debugger's room (issue 40.5): the Debug Adapter Protocol adapter (`dap*.py`), the
break/step/continue/why/VCD command-line clients, and a trace walked offline (`replay.py`,
`tracewalk.py`, `vcd.py`). It reaches a running PLC only as a client of the HTTP API
(`api.client`, `api.clicmds`' public names); the scan process never imports it
(tests/test_architecture.py).
"""
