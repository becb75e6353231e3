"""The machine a measurement ran on, measured (cores, CPU model, GPU), for the header of every bench report."""

from __future__ import annotations

import os
import platform
from datetime import UTC, datetime
from pathlib import Path


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo, else `platform.processor()`, else the architecture."""
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        for line in cpuinfo.read_text(errors="replace").splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


def usable_cores() -> int:
    """CPU cores this process may run on (its affinity mask, which a container limits), at least 1."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def gpu_name() -> str | None:
    """The first CUDA device's name when torch sees one, else None (torch imported only if already installed)."""
    try:
        import torch
    except ImportError:
        return None
    return torch.cuda.get_device_name(0) if torch.cuda.is_available() else None


def machine_line() -> str:
    """One line for a report, e.g. "2-core CPU (AMD EPYC 7B13), no GPU, x86_64, load average 1.2"."""
    gpu = gpu_name()
    load = f", load average {os.getloadavg()[0]:.1f}" if hasattr(os, "getloadavg") else ""
    return f"{usable_cores()}-core CPU ({cpu_model()}), {f'GPU {gpu}' if gpu else 'no GPU'}, {platform.machine()}{load}"


def report_header(title: str, machine: str, command: str | None = None, date: str | None = None) -> list[str]:
    """A bench report's first lines: `# title`, then the machine, the date (default: now, UTC) and the command."""
    lines = [f"# {title}", "", f"- machine: {machine}", f"- date: {date or now_utc()}"]
    return lines if command is None else [*lines, f"- command: `{command}`"]


def now_utc() -> str:
    """The current time as a report writes it, e.g. "2026-11-27 23:15 UTC"."""
    return datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
