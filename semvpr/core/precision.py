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

#: The job's precision as run (a key of AUTOCAST_DTYPE), bf16 where native until a job says otherwise, and
#: whether its fp32 matmuls and convolutions on a GPU use TF32.
_JOB: dict[str, str | bool] = {"precision": "bf16-mixed", "tf32": False}


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
def job_precision(requested: str, accelerator: str, tf32: bool = True) -> Iterator[str]:
    """Run a job in ``requested`` precision on ``accelerator``: semvpr's own autocast follows it; on a GPU,
    fp32 matmuls and cuDNN convolutions outside the fp32 sections use TF32 where ``tf32`` (else full fp32: an
    author's arithmetic). Yields the precision as run; restores the previous settings after."""
    precision = lightning_precision(requested, accelerator)
    gpu = str(accelerator).lower() in ("gpu", "cuda")
    before = dict(_JOB), torch.get_float32_matmul_precision(), torch.backends.cudnn.allow_tf32
    _JOB.update(precision=precision, tf32=gpu and tf32)
    if gpu:
        torch.set_float32_matmul_precision("high" if tf32 else "highest")
        torch.backends.cudnn.allow_tf32 = tf32
    try:
        yield precision
    finally:
        _JOB.update(before[0])
        torch.set_float32_matmul_precision(before[1])
        torch.backends.cudnn.allow_tf32 = before[2]


def running_precision() -> str:
    """The precision semvpr's own autocast runs in now (the current job's, else bf16-mixed)."""
    return str(_JOB["precision"])


def device_precision(device_type: str) -> str:
    """The running precision as it runs on a device of ``device_type``: a half type the device does not run
    natively is fp16 on a GPU and fp32 on a CPU (where fp16 autocast is not offered either)."""
    precision = running_precision()
    if precision == "bf16-mixed" and not bf16_native(device_type):
        precision = "16-mixed" if device_type == "cuda" else "32-true"
    return "32-true" if precision == "16-mixed" and device_type != "cuda" else precision


def autocast(device: torch.device | str = "cpu", enabled: bool = True) -> torch.autocast:
    """The job's autocast on ``device`` (``enabled=False``, full precision, or a half type the device does
    not run natively: a disabled autocast)."""
    device_type = torch.device(device).type
    dtype = AUTOCAST_DTYPE[device_precision(device_type)]
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
    """What a cached artifact computed on ``device`` in the running precision adds to its key: the device kind
    and the precision as it runs there (:func:`device_precision`: ``cpu/bf16-mixed``) and, on a CPU, the thread
    count of the job's frozen passes (``threads.frozen_threads``: a CPU reduction's bits depend on it); on a GPU
    its model instead of a thread count, and whether fp32 ran as TF32 (``cuda/NVIDIA H200/bf16-mixed/tf32``)."""
    device = torch.device(device)
    precision = device_precision(device.type)
    if device.type == "cpu":
        return {"frozen_threads": frozen_threads(), "compute": f"cpu/{precision}"}
    tf32 = "/tf32" if _JOB["tf32"] else ""
    return {"compute": f"{device.type}/{torch.cuda.get_device_name(device)}/{precision}{tf32}"}
