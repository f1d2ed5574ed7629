"""Markdown tables of an upscaler evaluation, for the docs and the terminal."""

from __future__ import annotations

from collections import defaultdict
from typing import Any


def _fmt(value: float | None, digits: int) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def markdown_table(cases: list[dict[str, Any]], checks: list[tuple[str, bool]]) -> str:
    """One table per scale: method rows, per-scene PSNR/FLIP, mean time and flicker."""
    by_scale: dict[float, list[dict[str, Any]]] = defaultdict(list)
    for c in cases:
        by_scale[c["scale"]].append(c)
    out: list[str] = []
    for scale in sorted(by_scale):
        rows = by_scale[scale]
        scenes = sorted({c["scene"] for c in rows})
        methods = list(dict.fromkeys(c["method"] for c in rows))
        render = rows[0]["render_size"]
        out.append(
            f"**{scale:g}x** (render {render}): PSNR dB / FLIP per scene; time ms median (p95)"
        )
        out.append("")
        head = ["method", "time ms", *scenes, "mean PSNR", "mean SSIM", "mean flicker"]
        out.append("| " + " | ".join(head) + " |")
        out.append("|" + "---|" * len(head))
        for m in methods:
            mine = [c for c in rows if c["method"] == m]
            cells = {c["scene"]: c for c in mine}
            per_scene = [
                f"{_fmt(cells[s]['psnr_db'], 2)} / {_fmt(cells[s]['flip'], 3)}"
                if s in cells
                else "-"
                for s in scenes
            ]
            med = sum(c["median_ms"] for c in mine) / len(mine)
            p95 = sum(c["p95_ms"] for c in mine) / len(mine)
            mean_psnr = sum(c["psnr_db"] for c in mine) / len(mine)
            mean_ssim = sum(c["ssim"] for c in mine) / len(mine)
            mean_flicker = sum(c["flicker"] for c in mine) / len(mine)
            out.append(
                f"| {m} | {med:.2f} ({p95:.2f}) | "
                + " | ".join(per_scene)
                + f" | {mean_psnr:.2f} | {mean_ssim:.4f} | {mean_flicker:.4f} |"
            )
        out.append("")
    if checks:
        out.append("Checks:")
        out.append("")
        out.extend(f"- {'PASS' if ok else 'FAIL'}: {text}" for text, ok in checks)
    return "\n".join(out)
