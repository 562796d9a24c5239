"""Shared test set-up: offline, deterministic, small thread count."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")

from tests.helpers import tiny_config, write_checkpoint  # noqa: E402 - after the offline switches


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A SynthCity-configured checkpoint (its data config has keys no other dataset knows)."""
    tmp = tmp_path_factory.mktemp("ckpt")
    write_checkpoint(tiny_config(tmp, "filter=attention"), tmp / "tested.ckpt")
    return tmp / "tested.ckpt"


@pytest.fixture(autouse=True)
def no_adopted_thread_plan() -> None:
    """Each test starts outside any job: no thread plan adopted by an earlier test's job."""
    from semvpr.core import threads

    threads._JOB["plan"] = None


def pytest_runtest_setup(item: pytest.Item) -> None:
    """Past ``SEMVPR_TESTS_UNTIL`` (seconds since the epoch; CI sets it for its slow group) a test not yet begun
    is skipped with that reason, so a group longer than CI's time ends with its skips counted, not killed."""
    until = os.environ.get("SEMVPR_TESTS_UNTIL")
    if until and time.time() > float(until):
        pytest.skip("CI's time budget (SEMVPR_TESTS_UNTIL) ran out before this test began")
