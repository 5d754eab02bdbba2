"""Self-tests of the harness, off by default: with JAXCAL_TEST_CRASH=<empty folder>, one test aborts
its process on the first try, one sleeps past its watchdog and one fails plainly. Under
`make test` the first is rerun in a fresh worker and passes, the second is killed twice (stacks
dumped) and reported failed, the third is reported failed without a rerun; the run goes on."""

import os
import pathlib
import time

import pytest

FOLDER = os.environ.get("JAXCAL_TEST_CRASH")
pytestmark = pytest.mark.skipif(not FOLDER, reason="harness self-test: set JAXCAL_TEST_CRASH to an empty folder")


def first_try(name: str) -> bool:
    """True the first time a test of this name runs with this folder."""
    marker = pathlib.Path(FOLDER) / name
    if marker.exists():
        return False
    marker.touch()
    return True


def test_crash_on_first_try_is_rerun():
    if first_try("crash"):
        os.abort()


@pytest.mark.watchdog(10)
def test_hang_is_stopped_by_the_watchdog():
    time.sleep(60)


def test_plain_failure_is_not_rerun():
    assert not (pathlib.Path(FOLDER) / "plain").exists(), "ran twice"
    first_try("plain")
    assert False, "plain failure"
