"""What supervises the processes of `softplc run` (issue 40.5): the command's start-up
(runcmd), the supervisor that starts, watches and restarts the scan and service processes,
the clean-up of a dead run's leftovers and systemd's readiness notice (sdnotify).

The top of the runtime: it may import the scan room, shared, serve and retain; none of them
may import it (tests/test_architecture.py SUBROOMS).
"""
