"""The machine a number was measured on, as a record keeps it: the CPU's model, the features that decide
semvpr's arithmetic (ARCHITECTURE §9) and the core count."""

from __future__ import annotations

import os
import platform
from pathlib import Path

#: CPU flags that decide the arithmetic: bf16 runs natively with AVX512-BF16 or AMX, else fp32 (AVX2).
ARITHMETIC_FLAGS = frozenset({"avx2", "avx512f", "avx512_bf16", "amx_bf16", "amx_tile"})


def _cpuinfo_field(name: str) -> str | None:
    """The first ``name : value`` of ``/proc/cpuinfo``, or None where there is none (not Linux)."""
    cpuinfo = Path("/proc/cpuinfo")
    if not cpuinfo.is_file():
        return None
    for line in cpuinfo.read_text(encoding="utf-8", errors="replace").splitlines():
        key, sep, value = line.partition(":")
        if sep and key.strip() == name:
            return value.strip()
    return None


def describe() -> dict[str, object]:
    """``{"cpu": model name, "flags": the arithmetic flags it has, "cores": os.cpu_count()}``."""
    flags = set((_cpuinfo_field("flags") or "").split())
    return {
        "cpu": _cpuinfo_field("model name") or platform.processor() or platform.machine(),
        "flags": sorted(flags & ARITHMETIC_FLAGS),
        "cores": os.cpu_count(),
    }
