"""What keeps retain across restarts (issue 40.5): the background writer and the state
directory's lock (writer), the encoding of retained values (codec) and the crash-safe file
store (store). What the scan does with them at a warm start is runtime/warmstart.py.

Imports only softplc.core and the runtime's leaves clock and realtime: never the scan loop,
the shared snapshot, the services or the supervisor (tests/test_architecture.py SUBROOMS).
"""
