"""The runtime (issue 40.5). The modules at this level run in the scan process (loop, runner,
scanproc, clock, realtime, download, prepare, compileproc, warmstart, trace...); the sub-rooms
hold the rest: shared/ (what the processes share: snapshot, board, channel, process flags),
retain/ (what keeps retain), serve/ (the service processes), supervise/ (what starts and
watches the processes) and offline/ (simulate and its scripts). tests/test_architecture.py
SUBROOMS holds the walls between them.
"""
