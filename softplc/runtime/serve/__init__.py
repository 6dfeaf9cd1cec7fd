"""The service processes over the shared snapshot (issue 40.5): comm starts the Modbus, HTTP
and OPC UA servers in their groups, timeslice asks the kernel for a service's scheduler slice.

Imports the shared sub-room and the service rooms (hmi, api, opcua, security); never the scan
loop, retain or the supervisor (tests/test_architecture.py SUBROOMS).
"""
