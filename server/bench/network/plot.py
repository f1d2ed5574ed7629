"""The figure of ``upcast bench network --plot``: bitrate against capacity over time,
one panel per profile (matplotlib, as the framegen benchmark's plot)."""

from __future__ import annotations

from pathlib import Path
from typing import Any


def _mbit(values: list[Any]) -> list[float]:
    return [float("nan") if v is None else v / 1e6 for v in values]


def plot(cases: list[dict[str, Any]], path: Path) -> str | None:
    """Write the PNG; a sentence instead when it cannot (no matplotlib, no case)."""
    if not cases:
        return "no profile measured: no plot"
    try:
        import matplotlib
    except ImportError:
        return "no plot: matplotlib is not installed (the game extra has it)"
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(cases), 1, figsize=(9, 2.6 * len(cases)), squeeze=False)
    for ax, case in zip(axes[:, 0], cases, strict=True):
        s = case["series"]
        t = s["t_s"]
        capacity = s["capacity_bps"]
        if any(c is not None for c in capacity):
            ax.step(t, _mbit(capacity), where="post", color="black", label="capacity")
        else:
            ax.plot([], [], color="black", label="capacity: unlimited")
        ax.plot(t, _mbit(s["bitrate_target_bps"]), label="encoder target")
        ax.plot(t, _mbit(s["link_delivered_bps"]), label="link delivered", alpha=0.7)
        if any(v is not None for v in s["page_received_bps"]):
            ax.plot(t, _mbit(s["page_received_bps"]), label="page received", alpha=0.7)
        ax.set_title(f"{case['name']}: {case['profile']}", fontsize=9)
        ax.set_ylabel("Mbit/s")
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper right")
    axes[-1, 0].set_xlabel("seconds into the window")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return None
