"""What every benchmark records about the machine it ran on (numbers are only comparable within one run)."""

from __future__ import annotations

import os
import platform

import torch


def machine_info() -> dict:
    return {
        "cpus": os.cpu_count(),
        "processor": platform.processor() or platform.machine(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "load_average": os.getloadavg(),
    }
