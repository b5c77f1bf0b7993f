"""Files made in the cell's folder belong to whoever made them: a command run as root in a folder of
the service's user would leave root's files there (a calibration, its backups folder, logs, the
history store, certificates and their private keys, mode 0600) that the service, running as that
user (configs/pick-cell.service: User=cell), could then neither replace nor read. Such a command
is refused before it writes anything, with the fix: run it as that user.
"""

from __future__ import annotations

import os
import pwd
from pathlib import Path

from cell.errors import ConfigError

ALLOW_ENV = "RUN_CELL_ALLOW_ROOT"  # "1": root may work in another user's folder (a developer's checkout, CI)


def user_name(uid: int) -> str:
    try:
        return pwd.getpwuid(uid).pw_name
    except KeyError:
        return f"uid {uid}"


def refuse_root_in_anothers_folder(command: str, folder: Path | None = None) -> None:
    """ConfigError when this process is root and `folder` (default: the working folder, where the
    config's relative paths lead) belongs to another user."""
    if os.geteuid() != 0 or os.environ.get(ALLOW_ENV) == "1":
        return
    folder = folder or Path.cwd()
    owner = folder.stat().st_uid
    if owner == 0:
        return
    name = user_name(owner)
    raise ConfigError(
        f"{command} runs as root in {folder}, which belongs to {name}: what it writes there (calibration, logs, "
        f"history, certificates) would be root's, and the service running as {name} could not replace or read it; "
        "nothing done",
        hint=f"run it as {name}: sudo -u {name} {command} ... (or runuser -u {name} -- {command} ...); "
        f"where no service uses this folder (a developer's checkout), {ALLOW_ENV}=1 lets root work in it",
    )
