"""Task functions for tests/test_fit_many.py, shipped to Ray workers by value (cloudpickle)."""

import os
from pathlib import Path

from dynbtf.fit_many import fit_one


def crash_once_then_fit(task):
    """Fit, but the first attempt of source 'b' kills its worker process at optimizer step 12
    (after the checkpoint of step 10): Ray retries the task, which resumes from that checkpoint."""
    marker = Path(task.output_dir) / f"{task.name}.crashed"

    def callback(info):
        if task.name == "b" and info["global_step"] == 12 and not marker.exists():
            marker.write_text("killed at step 12")
            os._exit(1)  # the worker dies as a killed process would: no cleanup, no exception

    return fit_one(task, callback=callback)
