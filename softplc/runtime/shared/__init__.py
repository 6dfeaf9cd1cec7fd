"""What the processes of `softplc run` share (issue 40.5): the snapshot in shared memory (shm,
shmcopy), the status board, the command channel, a snapshot's freshness, and the flags, ready
signals and names of the processes (procs).

Imports only softplc.core and the runtime's clock (a leaf): the scan, the services, the
supervisor and the Sparkplug node all meet here, so nothing here may know any of them
(tests/test_architecture.py SUBROOMS).
"""
