"""The real-content suite's checks, Markdown table and per-frame plot around the cut.

The checks are issue 19's statements about held-out photographs at 2x, evaluated
on whatever methods the run covered (a statement whose methods are missing is
left out, not passed).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

# Issue 19's margins, dB.
FIRST_NETWORK_MARGIN = 0.5
PAN_TEMPORAL_MARGIN = 2.0
STILL_TEMPORAL_MARGIN = 2.5
LATE_FALL_ALLOWED = 0.3
RESET_FRAMES = 4
RESET_SLACK = 0.2


def _per_source(
    methods: dict[str, Any], method: str, baseline: str, kind: str
) -> list[tuple[str, bool]]:
    """``method`` >= ``baseline`` on the mean of every content source (reports made
    before sources were kept have none: no check)."""
    ours = methods[method]["kinds"][kind].get("psnr_by_source", {})
    theirs = methods[baseline]["kinds"][kind].get("psnr_by_source", {})
    checks = []
    for source in ours:
        if source in theirs:
            gain = ours[source] - theirs[source]
            checks.append(
                (f"photos 2x {kind} on {source}: {method} >= {baseline} ({gain:+.2f})", gain >= 0)
            )
    return checks


def _every_image(
    methods: dict[str, Any], spatial: list[str], kind: str, margin: float
) -> list[tuple[str, bool]]:
    """Temporal >= the best spatial method on that photograph + ``margin``, on every
    held-out photograph (reports made before per-image figures were kept: no check).
    One line naming the photographs that miss, or the closest one when none does."""
    ours = methods["temporal"]["kinds"][kind].get("psnr_by_image")
    if not ours or not all("psnr_by_image" in methods[m]["kinds"][kind] for m in spatial):
        return []
    gains = {
        image: value - max(methods[m]["kinds"][kind]["psnr_by_image"][image] for m in spatial)
        for image, value in ours.items()
    }
    misses = {image: g for image, g in gains.items() if g < margin}
    shown = misses or dict([min(gains.items(), key=lambda item: item[1])])
    label = "below" if misses else "closest"
    detail = ", ".join(f"{image} {g:+.2f}" for image, g in shown.items())
    return [
        (
            f"photos 2x {kind}: temporal >= best spatial + {margin:g} dB on every photograph "
            f"({len(gains) - len(misses)} of {len(gains)}; {label}: {detail})",
            not misses,
        )
    ]


def real_content_checks(section: dict[str, Any]) -> list[tuple[str, bool]]:
    scale = section["scales"].get("2")
    if scale is None:
        return []
    methods: dict[str, Any] = scale["methods"]
    checks: list[tuple[str, bool]] = []

    def psnr(method: str, kind: str) -> float:
        return float(methods[method]["kinds"][kind]["psnr_db"])

    def curve(method: str, kind: str) -> list[float]:
        return list(methods[method]["kinds"][kind]["psnr_per_frame"])

    if "bicubic" in methods:
        for net in ("unet", "unetpp"):
            if net in methods:
                gain = psnr(net, "first") - psnr("bicubic", "first")
                checks.append(
                    (
                        f"photos 2x first frame: {net} >= bicubic + {FIRST_NETWORK_MARGIN:g} dB "
                        f"({gain:+.2f})",
                        gain >= FIRST_NETWORK_MARGIN,
                    )
                )
                checks += _per_source(methods, net, "bicubic", "first")
        if "easu_rcas" in methods:
            gain = psnr("easu_rcas", "first") - psnr("bicubic", "first")
            checks.append((f"photos 2x first frame: easu_rcas >= bicubic ({gain:+.2f})", gain >= 0))
    spatial = [m for m, v in methods.items() if not v["temporal"]]
    if "temporal" in methods and spatial:
        for kind, margin in (("pan", PAN_TEMPORAL_MARGIN), ("still", STILL_TEMPORAL_MARGIN)):
            best = max(spatial, key=lambda m: psnr(m, kind))
            gain = psnr("temporal", kind) - psnr(best, kind)
            start, end = methods["temporal"]["kinds"][kind]["measured_frames"]
            checks.append(
                (
                    f"photos 2x {kind} (frames {start}-{end - 1}): temporal >= best spatial "
                    f"({best}) + {margin:g} dB ({gain:+.2f})",
                    gain >= margin,
                )
            )
            checks += _every_image(methods, spatial, kind, margin)
    if "temporal" in methods:
        for kind in ("pan", "still"):
            c = curve("temporal", kind)
            start, end = methods["temporal"]["kinds"][kind]["measured_frames"]
            fall = c[start] - c[end - 1]
            checks.append(
                (
                    f"photos 2x {kind}: temporal frame {end - 1} >= frame {start} - "
                    f"{LATE_FALL_ALLOWED:g} dB ({c[end - 1]:.2f} against {c[start]:.2f})",
                    fall <= LATE_FALL_ALLOWED,
                )
            )
    if "temporal" in methods and "easu_rcas" in methods:
        t, e = curve("temporal", "cut"), curve("easu_rcas", "cut")
        cut = methods["temporal"]["kinds"]["cut"]["measured_frames"][0]
        after = range(cut, min(cut + RESET_FRAMES, len(t)))
        gaps = [t[i] - e[i] for i in after]
        checks.append(
            (
                f"photos 2x cut: temporal's frames 0-{len(gaps) - 1} after the cut each >= "
                f"easu_rcas - {RESET_SLACK:g} dB ({', '.join(f'{g:+.2f}' for g in gaps)})",
                all(g >= -RESET_SLACK for g in gaps),
            )
        )
    return checks


def real_content_table(section: dict[str, Any], checks: list[tuple[str, bool]]) -> str:
    """Per scale: methods against kinds, mean PSNR over the held-out photographs."""
    out = [
        f"Real content: {len(section['images'])} held-out photographs, display "
        f"{section['display_size']} ({', '.join(section['images'])})",
        "",
    ]
    for scale, data in section["scales"].items():
        methods: dict[str, Any] = data["methods"]
        kinds = list(section["kinds"])
        spans = next(iter(methods.values()))["kinds"]
        heads = [
            f"{k} (f{spans[k]['measured_frames'][0]}-{spans[k]['measured_frames'][1] - 1})"
            for k in kinds
        ]
        out.append(f"**{scale}x** (render {data['render_size']}): PSNR dB; time ms median (p95)")
        out.append("")
        out.append("| method | time ms | " + " | ".join(heads) + " |")
        out.append("|" + "---|" * (len(kinds) + 2))
        for m, v in methods.items():
            cells = [f"{v['kinds'][k]['psnr_db']:.2f}" for k in kinds]
            out.append(
                f"| {m} | {v['median_ms']:.2f} ({v['p95_ms']:.2f}) | " + " | ".join(cells) + " |"
            )
        out.append("")
        reference = section.get("multiframe_ls", {}).get("scales", {}).get(scale)
        if reference:
            out.extend(multiframe_ls_table(methods, reference))
    if checks:
        out.append("Checks (real content):")
        out.append("")
        out.extend(f"- {'PASS' if ok else 'FAIL'}: {text}" for text, ok in checks)
    return "\n".join(out)


def multiframe_ls_table(methods: dict[str, Any], reference: dict[str, Any]) -> list[str]:
    """Per photograph and covered kind: dB over the best spatial method of temporal
    (mean of its measured frames) and of the least-squares reference, raw and within
    the output clamp (mean of the reference's frames)."""
    spatial = [m for m, v in methods.items() if not v["temporal"]]
    kinds = list(reference)
    out = [
        "Multi-frame least squares (`--multiframe-ls`: offline, every frame's samples so far; "
        "clamped: within temporal's output clamp), dB over the best spatial method:",
        "",
        "| photograph | "
        + " | ".join(f"{k}: temporal / least squares / clamped" for k in kinds)
        + " |",
        "|" + "---|" * (len(kinds) + 1),
    ]
    for image in reference[kinds[0]]["psnr_by_image"]:
        cells = []
        for kind in kinds:
            best = max(
                (methods[m]["kinds"][kind]["psnr_by_image"][image] for m in spatial),
                default=None,
            )
            if best is None:
                cells.append("-")
                continue
            temporal = methods.get("temporal", {}).get("kinds", {}).get(kind, {})
            ours = temporal.get("psnr_by_image", {}).get(image)
            shown = f"{ours - best:+.2f}" if ours is not None else "-"
            raw = reference[kind]["psnr_by_image"][image] - best
            clamped = reference[kind]["psnr_clamped_by_image"][image] - best
            cells.append(f"{shown} / {raw:+.2f} / {clamped:+.2f}")
        out.append(f"| {image} | " + " | ".join(cells) + " |")
    out.append("")
    return out


def cut_plot(section: dict[str, Any], path: Path) -> None:
    """Per-frame PSNR of every method over the cut sequence (mean over photographs),
    one panel per scale; the cut is the dashed line."""
    import matplotlib

    matplotlib.use("Agg")  # no display on servers
    import matplotlib.pyplot as plt

    scales = list(section["scales"].items())
    fig, axes = plt.subplots(1, len(scales), figsize=(8 * len(scales), 5), dpi=110, squeeze=False)
    for ax, (scale, data) in zip(axes[0], scales, strict=True):
        cut = 0
        for m, v in data["methods"].items():
            c = v["kinds"]["cut"]["psnr_per_frame"]
            cut = v["kinds"]["cut"]["measured_frames"][0]
            ax.plot(range(len(c)), c, marker=".", label=m, linestyle="-" if v["temporal"] else "--")
        ax.axvline(cut - 0.5, color="grey", linestyle=":", label="cut (RESET)")
        ax.set_xlabel("frame")
        ax.set_ylabel("PSNR, dB (mean over held-out photographs)")
        ax.set_title(f"cut sequence, {scale}x to {section['display_size']}")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
