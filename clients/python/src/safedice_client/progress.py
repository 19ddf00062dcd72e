"""Progress shown on stderr while the client waits: a job's bar, an experiment's line."""

import sys
from typing import Any, Dict

Json = Dict[str, Any]


def progress_line(job: Json) -> None:
    """A job's progress bar, redrawn in place on stderr."""
    progress = job.get("progress") or {}
    fraction = progress.get("fraction") or 0.0
    width = 30
    bar = "#" * int(fraction * width) + "-" * (width - int(fraction * width))
    speed = progress.get("iterations_per_second")
    eta = progress.get("eta_seconds")
    extra = (f" {speed:,.0f} it/s" if speed else "") + (f" eta {eta:,.0f} s" if eta else "")
    sys.stderr.write(
        f"\r{job['id'][:8]} [{bar}] {fraction:6.1%} {job['status']}{extra}".ljust(79)
    )
    sys.stderr.flush()


def print_grid_progress(progress: Json) -> None:
    """An experiment's progress as one line on stderr: its jobs by status, in the server's
    words (the counts other than ``total`` are per status)."""
    counts = ", ".join(f"{n} {status}" for status, n in progress.items() if status != "total" and n)
    print(f"{progress['total']} jobs: {counts}", file=sys.stderr)
