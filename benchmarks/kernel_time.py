"""Kernel time of a cold training job with glibc's default allocator policy and with semvpr's, in one run.

    python benchmarks/kernel_time.py [--keep DIR] [--override KEY=VALUE ...]

Runs ``python -m semvpr.train filter=none trainer.max_epochs=3`` twice, each from an empty cache of its own
(SynthCity, its trunk pass, a short training, the test), in turn: once as semvpr runs it (``semvpr/__init__.py``
keeps freed blocks up to 1 GiB in the heap), once with glibc's own policy (a ``GLIBC_TUNABLES`` that
restates a default, ``glibc.malloc.tcache_count=7``, which makes semvpr leave the allocator alone; setting
a threshold itself would also switch off glibc's dynamic mmap threshold). Prints, per run, the user and
system CPU seconds of the job and its workers and their minor page faults; the recalls must be equal (the
allocator changes where memory comes from, never a number). Last line: ``default_sys_share=<sys/cpu>
semvpr_sys_share=<sys/cpu> default_faults=<n> semvpr_faults=<n> faults_ratio=<semvpr/default>
equal_recalls=<0|1> cpu_capability=<torch's kernels> bf16_native=<0|1>`` (the jobs run as this process does:
``ATEN_CPU_CAPABILITY=avx2 ONEDNN_MAX_CPU_ISA=AVX2`` in the environment stands for a CPU without AVX512, fp32).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import torch  # noqa: E402
from sweep_cost import REPO  # noqa: E402

from semvpr.core.errors import exit_on_user_error  # noqa: E402
from semvpr.core.precision import bf16_native  # noqa: E402

#: A glibc tunable at its default: in the environment, semvpr leaves glibc's whole policy as it is.
GLIBC_DEFAULT = {"GLIBC_TUNABLES": "glibc.malloc.tcache_count=7"}


def cold_job(work: Path, overrides: list[str], env: dict[str, str]) -> dict[str, float | dict]:
    """CPU seconds (user, sys), minor page faults and test recalls of one cold job under ``work``."""
    cmd = [
        sys.executable,
        "-m",
        "semvpr.train",
        "filter=none",
        "trainer.max_epochs=3",
        f"paths.cache_dir={work / 'cache'}",
        f"hydra.run.dir={work / 'run'}",
        *overrides,
    ]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    out = subprocess.run(cmd, cwd=REPO, env=os.environ | env, check=True, capture_output=True, text=True).stdout
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    last = json.loads(out.strip().splitlines()[-1])
    return {
        "user_s": after.ru_utime - before.ru_utime,
        "sys_s": after.ru_stime - before.ru_stime,
        "faults": after.ru_minflt - before.ru_minflt,
        "recalls": {k: v for k, v in last.items() if k.startswith("test/")},
    }


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--keep", type=Path, help="keep the runs under DIR (default: a temporary directory)")
    ap.add_argument("--override", action="append", default=[], metavar="KEY=VALUE")
    return ap


@exit_on_user_error
def main() -> None:
    args = parser().parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = args.keep or Path(tmp)
        runs = {}
        for name, env in (("semvpr", {}), ("default", GLIBC_DEFAULT)):
            runs[name] = cold_job(work / name, args.override, env)
            r = runs[name]
            share = r["sys_s"] / (r["user_s"] + r["sys_s"])
            print(f"{name}: user_s={r['user_s']:.1f} sys_s={r['sys_s']:.1f} sys_share={share:.3f} faults={r['faults']}")
    shares = {n: r["sys_s"] / (r["user_s"] + r["sys_s"]) for n, r in runs.items()}
    print(
        f"default_sys_share={shares['default']:.3f} semvpr_sys_share={shares['semvpr']:.3f} "
        f"default_faults={runs['default']['faults']} semvpr_faults={runs['semvpr']['faults']} "
        f"faults_ratio={runs['semvpr']['faults'] / runs['default']['faults']:.3f} "
        f"equal_recalls={int(runs['semvpr']['recalls'] == runs['default']['recalls'])} "
        f"cpu_capability={torch.backends.cpu.get_cpu_capability()} bf16_native={int(bf16_native('cpu'))}"
    )


if __name__ == "__main__":
    main()
