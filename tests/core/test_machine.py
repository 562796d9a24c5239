from pathlib import Path

import pytest

from semvpr.core import machine

CPUINFO = """processor\t: 0
vendor_id\t: AuthenticAMD
cpu family\t: 25
model\t\t: 17
model name\t: AMD EPYC
flags\t\t: fpu sse2 avx2 avx512f avx512_bf16 avx512_vnni

processor\t: 1
cpu family\t: 25
model\t\t: 17
model name\t: AMD EPYC
"""


def test_the_record_names_the_cpu_family_and_model_beside_its_name(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "cpuinfo").write_text(CPUINFO)
    monkeypatch.setattr(machine, "CPUINFO", tmp_path / "cpuinfo")
    record = machine.describe()
    assert record["cpu"] == "AMD EPYC" and record["cpu_family"] == "25" and record["cpu_model"] == "17"
    assert record["flags"] == ["avx2", "avx512_bf16", "avx512f"]  # "model name" is not read as "model"


def test_a_machine_without_cpuinfo_has_no_family(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(machine, "CPUINFO", tmp_path / "absent")
    record = machine.describe()
    assert record["cpu_family"] is None and record["cpu_model"] is None and record["flags"] == []


def test_the_record_names_the_instruction_set_caps_it_ran_under(monkeypatch: pytest.MonkeyPatch) -> None:
    """A number measured under ``ATEN_CPU_CAPABILITY=avx2`` on an AVX512 CPU is an AVX2 number: the record says so."""
    for name in machine.ISA_CAPS:
        monkeypatch.delenv(name, raising=False)
    assert machine.describe()["isa_caps"] == {}
    monkeypatch.setenv("ATEN_CPU_CAPABILITY", "avx2")
    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "AVX2")
    assert machine.describe()["isa_caps"] == {"ATEN_CPU_CAPABILITY": "avx2", "ONEDNN_MAX_CPU_ISA": "AVX2"}
