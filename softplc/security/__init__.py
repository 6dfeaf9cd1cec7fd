"""The security model of every door (issue 38): who is asking (users, sessions, keys, the
owner's key, certificates), what they may do (one role table keyed by command, one decision
point per request kind), which programs may be loaded (trusted keys, signatures), and the
evidence (the audit trail and its chain). HTTP, OPC UA, Modbus and the CLI ask here; this room
imports only core and the libraries it needs.
"""
