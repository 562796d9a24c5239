"""Run a benchmark and keep what it printed as a data file, with the command and the machine.

    python benchmarks/record.py benchmarks/results/<name>.json -- python benchmarks/<name>.py [ARGS ...]

Every benchmark prints its numbers, and ends with a ``key=value ...`` line. This runs the command,
passes its output through, and writes a JSON file: the command, the machine (CPU model, cores, the
load average when it started), the UTC start time, the wall time, every line it printed (``output``)
and the last line's fields (``last``). A failed command writes nothing. The docs state a benchmark's
numbers only from such a file (docs/trust.md, "Numbers in the docs").
"""

from __future__ import annotations

import argparse
import datetime
import os
import subprocess
import sys
import time
from pathlib import Path

from semvpr.core.errors import SemvprError, exit_on_user_error
from semvpr.core.io import write_json
from semvpr.core.machine import describe


def fields(line: str) -> dict[str, float | str]:
    """``a=1 b=2.5 c=x`` → {a: 1.0, b: 2.5, c: 'x'}; words without '=' are left out."""
    out: dict[str, float | str] = {}
    for item in line.split():
        key, sep, value = item.partition("=")
        if not sep or not key:
            continue
        try:
            out[key] = float(value)
        except ValueError:
            out[key] = value
    return out


def record(command: list[str]) -> dict[str, object]:
    """Run ``command`` (its output passed through) and return the record; one line if it fails."""
    started = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
    load = os.getloadavg() if hasattr(os, "getloadavg") else None
    t0 = time.perf_counter()
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    lines = []
    for line in proc.stdout:
        sys.stdout.write(line)
        lines.append(line.rstrip("\n"))
    if proc.wait() != 0:
        raise SemvprError(f"{' '.join(command)} failed (exit {proc.returncode}); nothing recorded")
    printed = [line for line in lines if line.strip()]
    return {
        "command": " ".join(command),
        "machine": {**describe(), "load_average_at_start": list(load) if load else None},
        "started_utc": started,
        "wall_s": round(time.perf_counter() - t0, 1),
        "output": printed,
        "last": fields(printed[-1]) if printed else {},
    }


@exit_on_user_error
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path, help="the JSON file to write")
    ap.add_argument("command", nargs=argparse.REMAINDER, help="-- then the benchmark's command line")
    args = ap.parse_args()
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        raise SemvprError("no command to run: benchmarks/record.py OUT.json -- python benchmarks/<name>.py ...")
    if command[0] == "python":
        command[0] = sys.executable  # the interpreter this runs under; the record keeps 'python'
    result = record(command)
    result["command"] = " ".join(["python", *command[1:]]) if command[0] == sys.executable else result["command"]
    write_json(args.out, result)


if __name__ == "__main__":
    main()
