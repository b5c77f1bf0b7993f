"""The one loopback rule: whether a host (a bind address, a Host header) is this machine only.

Every server of the cell (OPC UA, the screen, the robot server) asks this one function: on
loopback it may run without users; anywhere else it needs users and security. Only literal
loopback addresses (127.0.0.0/8, ::1, with or without brackets) and the name `localhost` count:
any other name may resolve anywhere (and a DNS answer can change after the check), so it is
treated as off the machine.
"""

from __future__ import annotations

import ipaddress


def is_loopback(host: str) -> bool:
    name = host.strip().strip("[]").lower()
    if name == "localhost":
        return True
    try:
        return ipaddress.ip_address(name).is_loopback
    except ValueError:
        return False
