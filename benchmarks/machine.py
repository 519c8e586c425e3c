"""What machine a benchmark ran on, for the headers of its results files.

Absolute timings depend on the CPU model as much as on the code (the same fit takes markedly longer on one
of this project's 2-core hosts than on another: docs/benchmarks.md), so every results file that quotes seconds
names it.
"""
from __future__ import annotations

import os
import platform
from pathlib import Path


def cpu_name() -> str:
    """The CPU's model name (``/proc/cpuinfo``), else ``platform.processor()``, else ``"unknown"``."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def describe() -> str:
    """``"x86_64 (AMD EPYC), 2 cores"``: architecture, CPU model and core count."""
    return f"{platform.machine()} ({cpu_name()}), {os.cpu_count()} cores"
