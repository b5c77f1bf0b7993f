"""Suite-wide settings: device and file locks go to a folder of this test session, not the machine's."""
import os

import pytest

from cell.locks import LOCK_DIR_ENV


@pytest.fixture(scope="session", autouse=True)
def private_lock_dir(tmp_path_factory):
    before = os.environ.get(LOCK_DIR_ENV)
    os.environ[LOCK_DIR_ENV] = str(tmp_path_factory.mktemp("locks"))
    yield
    if before is None:
        os.environ.pop(LOCK_DIR_ENV, None)
    else:
        os.environ[LOCK_DIR_ENV] = before
