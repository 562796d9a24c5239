"""benchmarks/gpu.py's record: written after every step, so a check stopped at its device limit or failing in one
step keeps what the others measured (the only GPU run once went past its limit and left nothing)."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

from tests.helpers import REPO


def _gpu_module():
    spec = importlib.util.spec_from_file_location("gpu_check", REPO / "benchmarks" / "gpu.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclass resolves its annotations there
    spec.loader.exec_module(module)
    return module


def test_each_step_is_recorded_as_it_ends_skipped_past_the_budget_and_a_failure_keeps_the_rest(tmp_path: Path) -> None:
    gpu = _gpu_module()
    record = tmp_path / "gpu.json"
    check = gpu.Check(budget_s=60.0, record_path=record, command="python benchmarks/gpu.py")
    seen = []

    def first() -> dict:
        return {"R@1": 50.0}

    def failing() -> None:
        seen.append(json.loads(record.read_text()))  # what a kill here would leave
        raise RuntimeError("CUDA error: out of memory")

    assert check.step("first", 1, first) == {"R@1": 50.0}
    assert check.step("second", 1, failing) is None
    assert check.step("too_long", 600, first) is None
    assert seen[0]["status"] == "running" and seen[0]["steps"]["first"]["result"] == {"R@1": 50.0}
    written = json.loads(record.read_text())
    assert written["steps"]["second"]["status"] == "failed" and "out of memory" in written["steps"]["second"]["error"]
    assert (
        written["steps"]["too_long"]["status"] == "skipped"
        and "needs about 600 s" in written["steps"]["too_long"]["why"]
    )
    check.say("gpu_check devices=cuda:0 tiny_sweep_s=41.5")
    check.write("failed")
    final = json.loads(record.read_text())
    assert final["status"] == "failed" and final["last"] == {"devices": "cuda:0", "tiny_sweep_s": 41.5}
    assert final["command"] == "python benchmarks/gpu.py" and final["machine"]["cores"] >= 1


def test_the_spy_names_the_modules_called_with_tensors_off_the_jobs_device() -> None:
    import torch
    from torch import nn

    gpu = _gpu_module()
    net = nn.Sequential(nn.Linear(3, 2), nn.ReLU())
    with gpu.PlacementSpy(torch.device("cuda")).on() as spy:  # a job on a GPU whose modules got CPU tensors
        net(torch.zeros(1, 3))
    assert spy.astray == {"Sequential": 1, "Linear": 1, "ReLU": 1} and spy.calls == 3
    with gpu.PlacementSpy(torch.device("cpu")).on() as spy:
        net(torch.zeros(1, 3))
        net[0](torch.zeros(4, 3))
    assert spy.astray == {} and spy.calls == 4
    net(torch.zeros(1, 3))  # the spy is off again
    assert spy.calls == 4
