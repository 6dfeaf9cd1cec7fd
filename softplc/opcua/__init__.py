"""OPC UA for softplc (issue 14): the server in the communication process (space.py,
program.py, server.py) and the `kind: opcua` driver with remote calls (driver.py)."""
