"""Compute precision: the job's ``trainer.precision``, with half precision only where the hardware runs it.

bf16 autocast with channels_last is several times faster than fp32 on CPUs with AVX512-BF16 or AMX and on
GPUs from Ampere on, but elsewhere it is emulated: on an AVX2-only CPU a VGG16 conv ran 8x *slower* in
bf16 than in fp32, and a V100 or T4 has no bf16 units. So ``bf16-mixed`` becomes ``32-true`` on such a CPU
and ``16-mixed`` (fp16 with Lightning's gradient scaler, the AMP recipe of those GPUs) on such a GPU.

Every autocast of semvpr's own (the trunk pass, masks, the retriever's description, the segmenters) goes
through :func:`autocast`, which follows the job's precision (:func:`job_precision`, set once per job), and
the sections that must stay fp32 (NetVLAD / SRAL soft-assignment, the VLAD sums, BoQ's renormalisation,
GeM's power, PCA) run under :func:`fp32`: autocast off and TF32 off, whatever the rest of the job allows.
Numbers therefore differ slightly between a bf16 and an fp32 machine (ARCHITECTURE §9).
"""

from __future__ import annotations

import functools
from collections.abc import Iterator
from contextlib import contextmanager

import torch

from semvpr.core.errors import SemvprError
from semvpr.core.threads import frozen_threads

#: The precisions a job may ask for (Lightning's flags; ``bf16`` and ``16`` are Lightning's short forms).
MIXED = {"bf16-mixed": "bf16-mixed", "bf16": "bf16-mixed", "16-mixed": "16-mixed", "16": "16-mixed"}
FULL = {"32-true": "32-true", "32": "32-true"}
AUTOCAST_DTYPE = {"bf16-mixed": torch.bfloat16, "16-mixed": torch.float16, "32-true": None}

#: The job's precision as run (a key of AUTOCAST_DTYPE): bf16 where native until a job says otherwise.
_JOB = {"precision": "bf16-mixed"}


@functools.cache
def bf16_native(device_type: str) -> bool:
    """Whether bf16 matmuls/convs run natively on this kind of device (emulation does not count)."""
    if device_type == "cuda":
        return torch.cuda.is_available() and torch.cuda.is_bf16_supported(including_emulation=False)
    if device_type == "cpu":
        try:
            return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
        except (AttributeError, RuntimeError):  # private API: absent means unknown, so assume not
            return False
    return False


def lightning_precision(requested: str, accelerator: str) -> str:
    """The precision a job asking for ``requested`` runs in on ``accelerator``: bf16 where native, else fp16
    mixed on a GPU and fp32 on a CPU; fp16 mixed only on a GPU; half weights (``*-true``) refused."""
    device_type = "cuda" if str(accelerator).lower() in ("gpu", "cuda") else "cpu"
    text = str(requested)
    if text in FULL:
        return "32-true"
    if text not in MIXED:
        raise SemvprError(
            f"trainer.precision={text!r} is not supported: semvpr runs bf16-mixed, 16-mixed (GPU) or 32-true "
            "(its fp32 sections, the soft-assignment and the VLAD sums, need fp32 weights)"
        )
    mixed = MIXED[text]
    if mixed == "16-mixed" and device_type == "cpu":
        raise SemvprError("trainer.precision=16-mixed needs a GPU (CPUs have no fp16 autocast); use bf16-mixed")
    if mixed == "bf16-mixed" and not bf16_native(device_type):
        return "16-mixed" if device_type == "cuda" else "32-true"
    return mixed


@contextmanager
def job_precision(requested: str, accelerator: str) -> Iterator[str]:
    """Run a job in ``requested`` precision on ``accelerator``: semvpr's own autocast follows it; on a GPU,
    fp32 matmuls outside the fp32 sections may use TF32. Yields the
    precision as run; restores the previous settings after."""
    precision = lightning_precision(requested, accelerator)
    before = _JOB["precision"], torch.get_float32_matmul_precision()
    _JOB["precision"] = precision
    if str(accelerator).lower() in ("gpu", "cuda"):
        torch.set_float32_matmul_precision("high")
    try:
        yield precision
    finally:
        _JOB["precision"] = before[0]
        torch.set_float32_matmul_precision(before[1])


def running_precision() -> str:
    """The precision semvpr's own autocast runs in now (the current job's, else bf16-mixed)."""
    return _JOB["precision"]


def autocast(device: torch.device | str = "cpu", enabled: bool = True) -> torch.autocast:
    """The job's autocast on ``device`` (``enabled=False``, full precision, or a half type the device does
    not run natively: a disabled autocast)."""
    device_type = torch.device(device).type
    dtype = AUTOCAST_DTYPE[_JOB["precision"]]
    if dtype is torch.bfloat16 and not bf16_native(device_type):
        dtype = torch.float16 if device_type == "cuda" else None
    if dtype is torch.float16 and device_type != "cuda":
        dtype = None
    return torch.autocast(device_type=device_type, dtype=dtype or torch.bfloat16, enabled=enabled and dtype is not None)


@contextmanager
def fp32(device_type: str) -> Iterator[None]:
    """A section that must run in fp32: autocast off, and TF32 off for matmuls and cuDNN convs (both restored
    after). Through torch's float32 matmul precision and cuDNN's switch, the settings Lightning reads too:
    mixing them with torch's per-backend ``fp32_precision`` makes torch refuse to report either."""
    matmul, conv = torch.get_float32_matmul_precision(), torch.backends.cudnn.allow_tf32
    torch.set_float32_matmul_precision("highest")
    torch.backends.cudnn.allow_tf32 = False
    try:
        with torch.autocast(device_type, enabled=False):
            yield
    finally:
        torch.set_float32_matmul_precision(matmul)
        torch.backends.cudnn.allow_tf32 = conv


def compute_key(device: torch.device | str) -> dict[str, str | int]:
    """What a cached artifact computed on ``device`` in the running precision adds to its key: on a CPU, the
    thread count of the job's frozen passes (``threads.frozen_threads``: a CPU reduction's bits depend on
    it); the device kind and precision off the CPU's default arithmetic (bf16 where native, else fp32): a
    GPU's, or another precision asked for."""
    device_type = torch.device(device).type
    precision = _JOB["precision"]
    default = "bf16-mixed" if bf16_native("cpu") else "32-true"
    key: dict[str, str | int] = {"frozen_threads": frozen_threads()} if device_type == "cpu" else {}
    if device_type != "cpu" or precision not in ("bf16-mixed", default):
        key["compute"] = f"{device_type}/{precision}"
    return key
