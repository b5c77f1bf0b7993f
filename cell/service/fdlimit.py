"""The process's open-file limit against what the service may hold.

Every connection, log file and device is a file descriptor. systemd's default soft limit
(`ulimit -n`) is 1024; the screen may hold `service.web.max_connections`, OPC UA
`service.opcua_limits.max_connections`, and the cell a few hundred more (logs, camera, arm,
threads' pipes, the image decoder). At start the soft limit is raised towards the hard one
if it is lower than that, and a warning says so when even the hard limit is too low
(configs/pick-cell.service sets LimitNOFILE).
"""

from __future__ import annotations

import logging
import resource
from typing import Any

log = logging.getLogger(__name__)

BASE_DESCRIPTORS = 256  # logs, devices, pipes and sockets of the cell besides its clients
ACCEPTED_AT_ONCE = 32 + 100  # sockets asyncio accepts in one go before their caps apply: the screen's, asyncua's
COMFORTABLE = 8192  # what the soft limit is raised to when it can (LimitNOFILE in configs/pick-cell.service)


def needed_descriptors(service: Any) -> int:
    """What the service may hold at most: its clients' caps, what is accepted before a cap applies, the cell's own."""
    return service.web.max_connections + service.opcua_limits.max_connections + ACCEPTED_AT_ONCE + BASE_DESCRIPTORS


def check_open_files(service: Any) -> str | None:
    """Raise the soft limit if it is below what the service needs and the hard limit allows;
    a warning (logged, and returned) if it stays below."""
    needed = needed_descriptors(service)
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft >= needed:
        return None
    ceiling = hard if hard != resource.RLIM_INFINITY else COMFORTABLE
    target = min(ceiling, max(needed, COMFORTABLE))
    if target > soft:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
            log.info("open-file limit raised from %d to %d (the service may need %d)", soft, target, needed)
            soft = target
        except (ValueError, OSError) as e:
            log.info("cannot raise the open-file limit from %d: %s", soft, e)
    if soft >= needed:
        return None
    warning = (
        f"the open-file limit is {soft} (hard {hard}), below the {needed} descriptors the service may need "
        f"(service.web.max_connections + service.opcua_limits.max_connections + {ACCEPTED_AT_ONCE + BASE_DESCRIPTORS}): "
        "set LimitNOFILE=8192 in its systemd unit (configs/pick-cell.service) or lower those caps"
    )
    log.warning(warning)
    return warning
