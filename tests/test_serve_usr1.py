"""SIGUSR1 to `run-cell serve` pauses and resumes through the command table, as it does for `run-cell`."""

import pytest

from cell.commands.serve import toggle_pause
from cell.core.commands import Command, VisionState
from tests.fake_service import FakeLineService


@pytest.fixture
def service():
    s = FakeLineService()
    yield s
    s.close()


def test_usr1_pauses_a_running_job_and_resumes_it(service):
    service.command(Command.START_CONTINUOUS)
    toggle_pause(service)
    assert service.snapshot().paused
    toggle_pause(service)
    snap = service.snapshot()
    assert not snap.paused and snap.vision_state is VisionState.CONTINUOUS_EXECUTION
    assert service.commands == [Command.START_CONTINUOUS, Command.PAUSE, Command.RESUME]


def test_usr1_with_no_job_is_refused_by_the_table_and_changes_nothing(service, caplog):
    toggle_pause(service)
    assert service.snapshot().vision_state is VisionState.READY and service.commands == []
    assert "SIGUSR1 ignored: Pause is not allowed in Ready" in caplog.text
