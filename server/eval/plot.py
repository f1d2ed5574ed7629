"""The speed-against-error picture: one point per method and scale."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path
from typing import Any

SUITE_LABELS = {"real_content": "photos"}


def speed_error_plot(cases: list[dict[str, Any]], path: Path, title: str) -> None:
    """Median ms (x, log) against mean PSNR over scenes (y); lines join a method's scales;
    dashed: ``+torch`` variants, dotted: ``+compiled``. Cases of another suite than the
    game's (``suite``: the held-out photographs) are their own series, square markers."""
    import matplotlib

    matplotlib.use("Agg")  # no display on servers
    import matplotlib.pyplot as plt

    points: dict[str, dict[float, list[tuple[float, float]]]] = defaultdict(
        lambda: defaultdict(list)
    )
    method_of: dict[str, str] = {}  # series label -> method
    for c in cases:
        suite = c.get("suite")
        label = (
            c["method"] if suite is None else f"{c['method']} ({SUITE_LABELS.get(suite, suite)})"
        )
        method_of[label] = c["method"]
        points[label][c["scale"]].append((c["median_ms"], c["psnr_db"]))
    fig, ax = plt.subplots(figsize=(8, 5.5), dpi=110)
    # A method's variants (+torch, +compiled) share its colour and differ in line style,
    # so the legend reads as methods, not as a dozen unrelated colours.
    colours: dict[str, str] = {}
    palette = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for method, by_scale in points.items():
        base, _, variant = method_of[method].partition("+")
        colour = colours.setdefault(base, palette[len(colours) % len(palette)])
        style = {"": "-", "torch": "--", "compiled": ":"}.get(variant, "-.")
        xs, ys, labels = [], [], []
        for scale in sorted(by_scale):
            pts = by_scale[scale]
            xs.append(sum(p[0] for p in pts) / len(pts))
            ys.append(sum(p[1] for p in pts) / len(pts))
            labels.append(f"{scale:g}x")
        marker = "o" if method == method_of[method] else "s"
        ax.plot(xs, ys, marker=marker, label=method, color=colour, linestyle=style)
        for x, y, label in zip(xs, ys, labels, strict=True):
            ax.annotate(label, (x, y), textcoords="offset points", xytext=(4, 4), fontsize=8)
    ax.set_xscale("log")
    ax.set_xlabel("time per frame, median ms (log scale)")
    ax.set_ylabel("PSNR against ground truth, dB (mean over scenes)")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
