"""Where the cell keeps what it can rebuild: the user's cache folder (XDG), pick-cell's part of it.

Only speed-ups live there (the OPC UA address space, the simulated plate's calibration): each
file is keyed by what it was made from, checked when read, and made again when it is missing,
stale or damaged.

Under systemd (configs/pick-cell.service: `CacheDirectory=pick-cell`) the folder systemd made
for the service, $CACHE_DIRECTORY, is used: the service user's home may be missing or read-only
there (`ProtectSystem=strict`), and that folder is the one the unit lets it write.
"""

from __future__ import annotations

import os
from pathlib import Path


def user_cache_dir(*parts: str) -> Path:
    """$CACHE_DIRECTORY/<parts> under systemd (its first folder), else $XDG_CACHE_HOME/pick-cell/<parts>
    (default ~/.cache/pick-cell/<parts>)."""
    systemd = os.environ.get("CACHE_DIRECTORY", "").split(":")[0]
    if systemd:
        return Path(systemd, *parts)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base, "pick-cell", *parts)
