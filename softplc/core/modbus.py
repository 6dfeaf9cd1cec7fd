"""The Modbus protocol's numbers, shared by the HMI slave (hmi/) and the remote-I/O driver
(devices/): the per-request quantity limits and the highest address.

Owns: constants of the Modbus Application Protocol V1.1b3 (section 6). Does not know:
sockets, pymodbus, frames, channels.
"""

from __future__ import annotations

MAX_ADDRESS = 0xFFFF  # 0-based addresses (protocol addresses) are 16-bit

MAX_READ_BITS = 2000  # FC 1, 2
MAX_READ_REGISTERS = 125  # FC 3, 4
MAX_WRITE_BITS = 1968  # FC 15
MAX_WRITE_REGISTERS = 123  # FC 16
MAX_RW_READ_REGISTERS = 125  # FC 23, its read part
MAX_RW_WRITE_REGISTERS = 121  # FC 23, its write part
