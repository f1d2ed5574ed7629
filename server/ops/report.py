"""The JSON benchmark report of DESIGN.md: machine, config, and measured cases."""

from __future__ import annotations

import json
import os
import platform
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from server.ops.machine import cpu_model


def machine_info() -> dict[str, Any]:
    """CPU model, thread counts and GPU (if torch sees one), for the report header."""
    cpu = cpu_model() or platform.processor() or platform.machine()
    info: dict[str, Any] = {
        "cpu": cpu,
        "cpu_count": os.cpu_count(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "gpu": None,
    }
    try:
        import torch

        info["torch"] = torch.__version__
        info["torch_threads"] = torch.get_num_threads()
        if torch.cuda.is_available():
            info["gpu"] = torch.cuda.get_device_name(0)
    except ImportError:
        pass
    return info


def summarize_ms(samples_ms: Iterable[float]) -> dict[str, float]:
    """Median, p95, mean, min and max of a list of milliseconds."""
    arr = np.asarray(list(samples_ms), dtype=np.float64)
    if arr.size == 0:
        return {"count": 0}
    return {
        "count": int(arr.size),
        "median_ms": float(np.median(arr)),
        "p95_ms": float(np.percentile(arr, 95)),
        "mean_ms": float(arr.mean()),
        "min_ms": float(arr.min()),
        "max_ms": float(arr.max()),
    }


@dataclass
class BenchReport:
    """Collects cases and writes the report; ``cases`` entries are free-form dicts
    that carry at least ``name`` and, for timings, ``median_ms`` and ``p95_ms``."""

    benchmark: str
    config: dict[str, Any]
    cases: list[dict[str, Any]] = field(default_factory=list)
    ratios: list[dict[str, Any]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    # Further top-level sections of a benchmark's own (the upscaler eval's real_content).
    sections: dict[str, Any] = field(default_factory=dict)

    def add_case(self, name: str, **values: Any) -> dict[str, Any]:
        case = {"name": name, **values}
        self.cases.append(case)
        return case

    def add_ratio(self, name: str, numerator: str, denominator: str, value: float) -> None:
        self.ratios.append(
            {"name": name, "numerator": numerator, "denominator": denominator, "ratio": value}
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "benchmark": self.benchmark,
            "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "machine": machine_info(),
            "config": self.config,
            "cases": self.cases,
            "ratios": self.ratios,
            "notes": self.notes,
            **self.sections,
        }

    def write(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(self.to_dict(), indent=2, default=_jsonable) + "\n")


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serializable: {type(value).__name__}")
