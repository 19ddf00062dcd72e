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
    """An experiment's progress as one line on stderr."""
    done = progress["total"] - progress["running"] - progress["queued"]
    print(f"{done} of {progress['total']} jobs finished ({progress['succeeded']} succeeded, "
          f"{progress['running']} running, {progress['queued']} queued)", file=sys.stderr)
