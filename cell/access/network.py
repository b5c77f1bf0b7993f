"""The one loopback rule: whether a host (a bind address, a Host header) is this machine only.

Every server of the cell (OPC UA, the screen, the robot server) asks this one function: on
loopback it may run without users; anywhere else it needs users and security. Only literal
loopback addresses (127.0.0.0/8, ::1, with or without brackets) and the name `localhost` count:
any other name may resolve anywhere (and a DNS answer can change after the check), so it is
treated as off the machine.

And the addresses a person can type: a wildcard bind (`0.0.0.0`, `::`) listed as this machine's
addresses in `run-cell serve`'s ready line (reachable_urls).
"""

from __future__ import annotations

import ipaddress
from collections.abc import Iterable


def is_loopback(host: str) -> bool:
    name = host.strip().strip("[]").lower()
    if name == "localhost":
        return True
    try:
        return ipaddress.ip_address(name).is_loopback
    except ValueError:
        return False


WILDCARDS_V4 = frozenset({"", "0.0.0.0"})
WILDCARDS_V6 = frozenset({"::", "0:0:0:0:0:0:0:0"})


def is_wildcard(host: str) -> bool:
    """A bind address meaning every interface (`0.0.0.0`, `::`): no one can type it into a browser."""
    name = host.strip().strip("[]")
    return name in WILDCARDS_V4 or name in WILDCARDS_V6


def machine_addresses() -> list[str]:
    """This machine's IP addresses, without dependencies: each interface's IPv4 address (Linux ioctl),
    the IPv6 addresses of /proc/net/if_inet6, and what the host name resolves to. Any source that fails
    is skipped: the ready line must never stop the service."""
    import socket

    found: list[str] = []
    try:
        import fcntl
        import struct

        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            for _, name in socket.if_nameindex():
                try:
                    ifreq = fcntl.ioctl(s.fileno(), 0x8915, struct.pack("256s", name.encode()[:15]))  # SIOCGIFADDR
                except OSError:
                    continue  # an interface without an IPv4 address
                found.append(socket.inet_ntoa(ifreq[20:24]))
    except (ImportError, OSError):
        pass
    try:
        with open("/proc/net/if_inet6", encoding="ascii") as f:
            for line in f:
                raw = line.split()[0]
                found.append(str(ipaddress.IPv6Address(bytes.fromhex(raw))))
    except (OSError, ValueError, IndexError):
        pass
    try:
        for *_, sockaddr in socket.getaddrinfo(socket.gethostname(), None, proto=socket.IPPROTO_TCP):
            found.append(str(sockaddr[0]))
    except OSError:
        pass
    return found


def reachable_hosts(host: str, addresses: Iterable[str] | None = None) -> list[str]:
    """What to tell a person to type for a server bound to `host`: a specific address or name as it is;
    for a wildcard, the machine's addresses of that family (`0.0.0.0`: IPv4, `::`: IPv6), link-local
    ones left out (unusable without an interface), loopback last. `addresses`: the machine's addresses
    (machine_addresses() when None; tests pass their own)."""
    if not is_wildcard(host):
        return [host.strip()]
    version = 6 if host.strip().strip("[]") in WILDCARDS_V6 else 4
    others: list[str] = []
    for text in machine_addresses() if addresses is None else addresses:
        try:
            ip = ipaddress.ip_address(text.split("%")[0])
        except ValueError:
            continue
        if ip.version != version or ip.is_loopback or ip.is_link_local or ip.is_unspecified:
            continue
        if str(ip) not in others:
            others.append(str(ip))
    return [*others, "::1" if version == 6 else "127.0.0.1"]


def url_host(host: str) -> str:
    """A host as it goes into a URL: an IPv6 address in brackets."""
    name = host.strip().strip("[]")
    return f"[{name}]" if ":" in name else name


def reachable_urls(scheme: str, host: str, port: int, path: str = "/", addresses: Iterable[str] | None = None) -> str:
    """`scheme://host:port/path` for each reachable host (reachable_hosts), comma-separated: the ready line's
    addresses."""
    return ", ".join(f"{scheme}://{url_host(h)}:{port}{path}" for h in reachable_hosts(host, addresses))
