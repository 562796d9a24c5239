"""Compute precision: bf16 autocast only where the hardware runs it natively.

bf16 autocast with channels_last is several times faster than fp32 on CPUs with AVX512-BF16 or
AMX and on recent GPUs, but oneDNN emulates it elsewhere: on an AVX2-only CPU a VGG16 conv ran
8x *slower* in bf16 than in fp32. So every autocast in semvpr goes through ``autocast`` below,
and Lightning's ``bf16-mixed`` falls back to ``32-true`` the same way. Numbers therefore differ
slightly between a bf16 and an fp32 machine (ARCHITECTURE §9).
"""

from __future__ import annotations

import functools

import torch


@functools.cache
def bf16_native(device_type: str) -> bool:
    """Whether bf16 matmuls/convs run natively on this kind of device."""
    if device_type == "cuda":
        return torch.cuda.is_available() and torch.cuda.is_bf16_supported()
    if device_type == "cpu":
        try:
            return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
        except (AttributeError, RuntimeError):  # private API: absent means unknown, so assume not
            return False
    return False


def autocast(device: torch.device | str = "cpu", enabled: bool = True) -> torch.autocast:
    """bf16 autocast where the device runs bf16 natively (and ``enabled``), else a disabled autocast."""
    device_type = torch.device(device).type
    return torch.autocast(device_type=device_type, dtype=torch.bfloat16, enabled=enabled and bf16_native(device_type))


def lightning_precision(requested: str, accelerator: str) -> str:
    """``requested`` unless it is bf16 on hardware that would only emulate it (then ``32-true``)."""
    device_type = "cuda" if accelerator in ("gpu", "cuda") else "cpu"
    if requested.startswith("bf16") and not bf16_native(device_type):
        return "32-true"
    return requested
