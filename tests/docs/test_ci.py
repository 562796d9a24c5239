"""CI's script: its slow group runs within CI's time, skipping (and counting) what it has no time to begin."""

from __future__ import annotations

import re
import time
from pathlib import Path

import pytest

from tests.conftest import pytest_runtest_setup

CI = Path(__file__).resolve().parents[2] / ".ci" / "run"


def test_a_test_not_begun_before_the_deadline_is_skipped_naming_it(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("SEMVPR_TESTS_UNTIL", str(time.time() + 3600))
    pytest_runtest_setup(None)  # before the deadline: runs
    monkeypatch.setenv("SEMVPR_TESTS_UNTIL", str(time.time() - 1))
    with pytest.raises(pytest.skip.Exception, match="SEMVPR_TESTS_UNTIL"):
        pytest_runtest_setup(None)
    monkeypatch.delenv("SEMVPR_TESTS_UNTIL")
    pytest_runtest_setup(None)  # no deadline: runs


def test_ci_gives_only_the_slow_group_a_deadline_and_runs_it_last() -> None:
    runs = [line for line in CI.read_text().splitlines() if "python -m pytest" in line]
    assert [bool(re.search(r"-m slow\b", line)) for line in runs] == [False, False, True]
    assert all("SEMVPR_TESTS_UNTIL" not in line for line in runs[:2])
    deadline = re.search(r"SEMVPR_TESTS_UNTIL=\$\(\(START \+ (\d+) \* 60\)\)", runs[2])
    assert deadline and int(deadline.group(1)) < 90
