"""The machine a number was measured on, as a record keeps it: the CPU's model name, family and model number
(two CPUs of one name and the same flags may still give other bits, ARCHITECTURE §9), the features that
decide semvpr's arithmetic and the core count."""

from __future__ import annotations

import os
import platform
from pathlib import Path

#: CPU flags that decide the arithmetic: bf16 on AVX512 (natively with AVX512-BF16 or AMX), else fp32 (AVX2).
ARITHMETIC_FLAGS = frozenset({"avx2", "avx512f", "avx512_bf16", "amx_bf16", "amx_tile"})
CPUINFO = Path("/proc/cpuinfo")
#: Settings that cap the instruction set torch and oneDNN use below what the CPU has (a CPU without AVX512
#: reproduced on one with it: ``ATEN_CPU_CAPABILITY=avx2 ONEDNN_MAX_CPU_ISA=AVX2`` runs fp32).
ISA_CAPS = ("ATEN_CPU_CAPABILITY", "ONEDNN_MAX_CPU_ISA")


def _cpuinfo() -> dict[str, str]:
    """The first processor's ``name : value`` fields of ``/proc/cpuinfo`` ({} where there is none: not Linux)."""
    if not CPUINFO.is_file():
        return {}
    fields: dict[str, str] = {}
    for line in CPUINFO.read_text(encoding="utf-8", errors="replace").splitlines():
        key, sep, value = line.partition(":")
        if not sep:
            if fields:  # the blank line after the first processor's block
                break
            continue
        fields.setdefault(key.strip(), value.strip())
    return fields


def describe() -> dict[str, object]:
    """``{"cpu": model name, "cpu_family": …, "cpu_model": … (None where unknown), "flags": the arithmetic flags
    it has, "cores": os.cpu_count(), "isa_caps": the instruction-set caps the environment sets ({}: none)}``."""
    info = _cpuinfo()
    flags = set(info.get("flags", "").split())
    return {
        "cpu": info.get("model name") or platform.processor() or platform.machine(),
        "cpu_family": info.get("cpu family"),
        "cpu_model": info.get("model"),
        "flags": sorted(flags & ARITHMETIC_FLAGS),
        "cores": os.cpu_count(),
        "isa_caps": {name: os.environ[name] for name in ISA_CAPS if name in os.environ},
    }


def short_name(described: dict[str, object]) -> str:
    """A machine as :func:`describe` recorded it, in a few words: the CPU and the widest units its arithmetic
    runs on (``Intel(R) Xeon(R) ... (AMX)``; AVX512-BF16; AVX512, where oneDNN runs bf16 by conversion; AVX2:
    fp32)."""
    flags = set(described.get("flags", ()))  # type: ignore[arg-type]
    units = next(
        (name for flag, name in (("amx_tile", "AMX"), ("avx512_bf16", "AVX512-BF16"), ("avx512f", "AVX512"))
         if flag in flags),
        "AVX2",
    )  # fmt: skip
    return f"{described.get('cpu', '?')} ({units})"
