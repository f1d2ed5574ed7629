"""What a setting is expected to cost and to look like, from the table and from what
this session measures.

**Picture.** PSNR against the game's ground truth (figures.py) for the method at the
render scale, averaged over the evaluation's scenes of the current scene class,
interpolated linearly in log(scale) between the measured scales and extended with
the end slopes outside them. With frame generation every other frame is predicted:
its error adds (in mean squared error) the predictor's own error for that scene,
and the two frames' errors average. Encoding below the display size loses what the
encoded-size benchmark measured on the decoded picture at that render scale
(interpolated in log(render scale), never below 0): little where the render was
smaller than the encoded size anyway (0.03 dB encoding at 2x a render at 4x), more
where the upscaler had detail to keep.

**Time.** Each stage is predicted from its own measurement, never from the table
alone:

- *render*: a fixed part plus a part proportional to render pixels (a ray caster's
  cost; the fixed part is the scene update and the frame's bookkeeping), fitted to
  the render stage's medians measured at each scale the session ran at (smoothed
  per scale); with one scale measured, ``FIXED_SHARE`` of it is taken as fixed. With
  frame generation a displayed frame costs a share of a full render: half a full
  render plus a dynamic-only draw until measured, then what the render stage's median
  shows against a full render at that size (on a loaded host it was no cheaper);
- *upscale*: the table's time for the method and scale (at this display size),
  times a ratio learned online from the measured upscale stage: per method while it
  runs, and for one that has not run yet the larger of the last measured ratio of any
  method and the host's slowdown (the render measured against the table's render),
  never under 1; frame generation adds half a prediction;
- *encode*: as measured at each encoded size; at one not measured yet, the nearest
  measured one times the benchmark's time ratio between the two sizes.

The CPU a setting takes is the sum of the stage medians at its frame rate (the
target times the setting's ``rate``), in cores: the three stages run in separate
processes on the same cores. A stage's time is per frame, whatever the rate.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

from server.session.quality.figures import SpeedErrorFigures
from server.session.quality.scene import SCENES_OF_CLASS, SceneClass

SMOOTHING = 0.5  # weight of a new measurement in the learned figures
MAX_SLOWDOWN = 4.0
FIXED_SHARE = 0.3  # of a render measured at one scale only, taken as its fixed part
DYNAMIC_DRAW_SHARE = 0.2
MIN_FG_RENDER_SHARE = 0.2
MAX_FG_RENDER_SHARE = 1.5  # a dynamic-only tick against a full render (moving objects)
STAGES = ("render", "upscale", "encode")


@dataclass(frozen=True)
class Setting:
    """What the controller chooses: method, render scale (display / render), whether
    every other frame is predicted, and the encoded scale (display / encoded)."""

    method: str
    scale: float
    frame_generation: bool = False
    encode_scale: float = 1.0
    rate: float = 1.0  # the frame rate, as a fraction of the goal's target

    def describe(self, target_fps: float | None = None) -> str:
        fg = ", frame generation" if self.frame_generation else ""
        enc = f", encoded at 1/{self.encode_scale:g}" if self.encode_scale != 1.0 else ""
        rate = ""
        if abs(self.rate - 1.0) > 1e-6:
            rate = (
                f", at {target_fps * self.rate:.3g} fps"
                if target_fps is not None
                else f", at {self.rate:.3g} of the frame rate"
            )
        return f"{self.method} at {self.scale:g}x{fg}{enc}{rate}"


@dataclass(frozen=True)
class StageTimes:
    """Predicted milliseconds per frame of each stage: median and p95."""

    p50: Mapping[str, float]
    p95: Mapping[str, float]

    def cpu_cores(self, fps: float) -> float:
        """Cores the three stages keep busy at ``fps`` (medians)."""
        return sum(self.p50.get(s, 0.0) for s in STAGES) * fps / 1000.0


def _interp_log(scales: tuple[float, ...], values: tuple[float, ...], scale: float) -> float:
    """Linear in log(scale) through the points, the end slopes outside them."""
    if len(scales) == 1:
        return values[0]
    x = math.log(scale)
    xs = [math.log(s) for s in scales]
    i = 0
    while i < len(xs) - 2 and x > xs[i + 1]:
        i += 1
    x0, x1 = xs[i], xs[i + 1]
    t = (x - x0) / (x1 - x0)
    return values[i] + t * (values[i + 1] - values[i])


def _psnr_to_mse(db: float) -> float:
    return float(10.0 ** (-db / 10.0))


def _mse_to_psnr(mse: float) -> float:
    return -10.0 * math.log10(max(mse, 1e-12))


@dataclass
class LearnedCosts:
    """The session's own measurements, smoothed; None until measured."""

    render_ms_at: dict[float, tuple[float, float]] = field(default_factory=dict)  # p50, p95
    encode_ms_at: dict[float, tuple[float, float]] = field(default_factory=dict)  # by encode scale
    upscale_ratio: dict[str, float] = field(default_factory=dict)
    last_upscale_ratio: float | None = None
    upscale_p95_over_p50: float | None = None
    fg_render_share: float | None = None  # render p50 with frame generation / without


def _smooth(old: float | None, new: float) -> float:
    return new if old is None else (1.0 - SMOOTHING) * old + SMOOTHING * new


class QualityModel:
    def __init__(self, figures: SpeedErrorFigures, display_pixels: int) -> None:
        self.figures = figures
        self.display_pixels = display_pixels
        self.learned = LearnedCosts()

    def methods(self) -> list[str]:
        return sorted(self.figures.methods)

    def render_pixels(self, scale: float) -> float:
        return self.display_pixels / (scale * scale)

    # -- picture ---------------------------------------------------------------------

    def encode_scales(self) -> list[float]:
        """The encoded scales the benchmark measured (just 1 without its figures)."""
        enc = self.figures.encode
        return [1.0] if enc is None else list(enc.scales)

    def encode_loss_db(self, render_scale: float, encode_scale: float) -> float:
        """PSNR lost by encoding at ``encode_scale`` a picture rendered at ``render_scale``."""
        enc = self.figures.encode
        if encode_scale == 1.0 or enc is None:
            return 0.0
        if encode_scale not in enc.scales:
            return math.inf  # not measured: never chosen
        column = enc.scales.index(encode_scale)
        points = [(s, row[column]) for s, row in zip(enc.render_scales, enc.loss_db, strict=True)]
        known = [(s, v) for s, v in points if v is not None]
        if not known:
            return math.inf
        scales, values = zip(*known, strict=True)
        return max(0.0, _interp_log(tuple(scales), tuple(values), render_scale))

    def expected_psnr(self, setting: Setting, scene: SceneClass) -> float:
        loss = self.encode_loss_db(setting.scale, setting.encode_scale)
        return self._rendered_psnr(setting, scene) - loss

    def _rendered_psnr(self, setting: Setting, scene: SceneClass) -> float:
        method = self.figures.methods[setting.method]
        scenes = self._scenes(scene, method.psnr_db)
        upscaled = [_interp_log(method.scales, method.psnr_db[s], setting.scale) for s in scenes]
        if not setting.frame_generation:
            return sum(upscaled) / len(upscaled)
        mses = []
        for scene_name, db in zip(scenes, upscaled, strict=True):
            rendered = _psnr_to_mse(db)
            predicted_db = self.figures.predict_psnr_db.get(scene_name)
            extra = 0.0 if predicted_db is None else _psnr_to_mse(predicted_db)
            mses.append((rendered + (rendered + extra)) / 2.0)
        return sum(_mse_to_psnr(m) for m in mses) / len(mses)

    def _scenes(self, scene: SceneClass, available: Mapping[str, object]) -> list[str]:
        wanted = [s for s in SCENES_OF_CLASS[scene] if s in available]
        return wanted or list(available)

    # -- time ------------------------------------------------------------------------

    def table_upscale_ms(self, method: str, scale: float) -> tuple[float, float]:
        """The table's (median, p95) for this method and scale at this display size."""
        m = self.figures.methods[method]
        size = self.display_pixels / self.figures.display_pixels
        p50 = max(0.1, _interp_log(m.scales, m.median_ms, scale)) * size
        p95 = max(0.1, _interp_log(m.scales, m.p95_ms, scale)) * size
        return p50, p95

    def learn(self, setting: Setting, p50: Mapping[str, float], p95: Mapping[str, float]) -> None:
        """Fold one window's measured stage times (ms) taken under ``setting`` in."""
        lc = self.learned
        if _usable(p50, "render") and setting.frame_generation and lc.render_ms_at:
            # What a displayed frame's render costs with frame generation, against a full
            # render at that size: learned, since the dynamic-only draw's share and the
            # game's per-frame work that frame generation does not halve vary by scene.
            full, _ = self._render_ms(self.render_pixels(setting.scale))
            share = min(MAX_FG_RENDER_SHARE, max(MIN_FG_RENDER_SHARE, p50["render"] / full))
            lc.fg_render_share = _smooth(lc.fg_render_share, share)
        if _usable(p50, "render") and _usable(p95, "render") and not setting.frame_generation:
            key = round(setting.scale, 4)
            old = lc.render_ms_at.get(key)
            lc.render_ms_at[key] = (
                _smooth(None if old is None else old[0], p50["render"]),
                _smooth(None if old is None else old[1], max(p50["render"], p95["render"])),
            )
        if _usable(p50, "encode") and _usable(p95, "encode"):
            key = setting.encode_scale
            old_e = lc.encode_ms_at.get(key)
            lc.encode_ms_at[key] = (
                _smooth(None if old_e is None else old_e[0], p50["encode"]),
                _smooth(None if old_e is None else old_e[1], max(p50["encode"], p95["encode"])),
            )
        if _usable(p50, "upscale"):
            measured = p50["upscale"]
            if setting.frame_generation:
                # Half the frames are predicted first: that part is the predictor's.
                measured = max(0.1, measured - self._predict_ms(setting) / 2.0)
            table_p50, _ = self.table_upscale_ms(setting.method, setting.scale)
            ratio = measured / table_p50
            lc.upscale_ratio[setting.method] = _smooth(lc.upscale_ratio.get(setting.method), ratio)
            lc.last_upscale_ratio = ratio
            if _usable(p95, "upscale") and not setting.frame_generation:
                spread = max(1.0, p95["upscale"] / p50["upscale"])
                lc.upscale_p95_over_p50 = _smooth(lc.upscale_p95_over_p50, spread)

    def _predict_ms(self, setting: Setting) -> float:
        f = self.figures
        px = self.render_pixels(setting.scale)
        return (
            f.predict_ms * px / f.predict_pixels * max(1.0, self.learned.last_upscale_ratio or 1.0)
        )

    def predict(self, setting: Setting) -> StageTimes:
        lc = self.learned
        px = self.render_pixels(setting.scale)
        r50, r95 = self._render_ms(px)
        if setting.frame_generation:
            r50 *= lc.fg_render_share or (1.0 + DYNAMIC_DRAW_SHARE) / 2.0
        # A method not run yet: the host's slowdown seen on the others, but never faster
        # than the table (a cheap method running fast says little about a costly one).
        ratio = lc.upscale_ratio.get(
            setting.method, max(1.0, lc.last_upscale_ratio or 1.0, self.host_slowdown())
        )
        u50, u95 = self.table_upscale_ms(setting.method, setting.scale)
        u50 *= ratio
        u95 = u50 * lc.upscale_p95_over_p50 if lc.upscale_p95_over_p50 else u95 * ratio
        if setting.frame_generation:
            predict = self._predict_ms(setting)
            u50 += predict / 2.0
            u95 += predict
        e50, e95 = self._encode_ms(setting.encode_scale)
        return StageTimes(
            p50={"render": r50, "upscale": u50, "encode": e50},
            p95={"render": r95, "upscale": u95, "encode": e95},
        )

    def host_slowdown(self) -> float:
        """How much slower than the table's machine this host runs the stages now: the
        render measured against the table's render time at the same size (both from the
        idle machine's reports), within [1, MAX_SLOWDOWN]. The processes of a session
        share cores, so a stage that has not run yet slows about as much as one that has."""
        f = self.figures
        slowest = 1.0
        for scale, (p50, _) in self.learned.render_ms_at.items():
            prior = f.render_ms * self.render_pixels(scale) / f.predict_pixels
            slowest = max(slowest, p50 / prior)
        return min(MAX_SLOWDOWN, slowest)

    def _encode_ms(self, encode_scale: float) -> tuple[float, float]:
        """(p50, p95) of the encoder at this encoded scale: measured, or the nearest
        measured scale's times the benchmark's ratio; 0 before anything was measured."""
        measured = self.learned.encode_ms_at
        if encode_scale in measured:
            return measured[encode_scale]
        if not measured:
            return 0.0, 0.0
        nearest = min(measured, key=lambda e: abs(math.log(e) - math.log(encode_scale)))
        ratio = self._encode_ratio(encode_scale) / self._encode_ratio(nearest)
        m50, m95 = measured[nearest]
        return m50 * ratio, m95 * ratio

    def _encode_ratio(self, encode_scale: float) -> float:
        enc = self.figures.encode
        if enc is None or encode_scale not in enc.scales:
            return 1.0
        return enc.ms_ratio[enc.scales.index(encode_scale)]

    def _render_ms(self, px: float) -> tuple[float, float]:
        """(p50, p95) of a full render of ``px`` pixels: a line through what was
        measured, or the table's render time before anything was."""
        points = [
            (self.render_pixels(scale), ms) for scale, ms in self.learned.render_ms_at.items()
        ]
        if not points:
            per_px = self.figures.render_ms / self.figures.predict_pixels
            return per_px * px, per_px * px
        if len(points) == 1:
            (px0, (m50, m95)) = points[0]
            return (_fixed_plus(m50, px, px0), _fixed_plus(m95, px, px0))
        return _line(points, px, 0), _line(points, px, 1)


def _fixed_plus(ms: float, px: float, px0: float) -> float:
    return ms * (FIXED_SHARE + (1.0 - FIXED_SHARE) * px / px0)


def _line(points: list[tuple[float, tuple[float, float]]], px: float, column: int) -> float:
    """Least squares ms = a + b * px over the points, with a, b >= 0."""
    xs = [p for p, _ in points]
    ys = [ms[column] for _, ms in points]
    n = len(xs)
    mx, my = sum(xs) / n, sum(ys) / n
    var = sum((x - mx) ** 2 for x in xs)
    b = (
        max(0.0, sum((x - mx) * (y - my) for x, y in zip(xs, ys, strict=True)) / var)
        if var
        else 0.0
    )
    a = max(0.0, my - b * mx)
    if a == 0.0 and mx > 0:
        b = my / mx
    return a + b * px


def _usable(figures: Mapping[str, float], stage: str) -> bool:
    value = figures.get(stage)
    return value is not None and math.isfinite(value) and value > 0.0


def scale_ladder(low: float, high: float, step: float = 0.25) -> list[float]:
    """Render scales from ``low`` to ``high`` in ``step`` (both ends included)."""
    out: list[float] = []
    value = low
    while value < high - 1e-9:
        out.append(round(value, 4))
        value += step
    out.append(round(high, 4))
    return out


def settings_grid(
    methods: Iterable[str],
    scales: Iterable[float],
    frame_generation: Iterable[bool],
    encode_scales: Iterable[float] = (1.0,),
    rates: Iterable[float] = (1.0,),
) -> list[Setting]:
    """Every combination, less an encoded size below the render size (it would throw
    the upscaler's work away)."""
    encodes = list(encode_scales)
    fgs = list(frame_generation)
    rate_list = list(rates)
    return [
        Setting(m, s, fg, e, r)
        for r in rate_list
        for m in methods
        for s in scales
        for fg in fgs
        for e in encodes
        if e <= s + 1e-6
    ]


# Fractions of the target frame rate the controller may run at: whole divisions of a
# display's refresh at 30 and 60 fps targets (30, 20, 15, 10 fps of 30), so every frame
# shows for the same number of refreshes.
RATE_LADDER = (1.0, 2.0 / 3.0, 0.5, 1.0 / 3.0)
MIN_LADDER_FPS = 10.0  # below this a stream is a slide show: never chosen


def rate_ladder(target_fps: float) -> list[float]:
    """The ladder's fractions whose frame rate stays at or above ``MIN_LADDER_FPS``
    (always the full rate)."""
    return [r for r in RATE_LADDER if r == 1.0 or target_fps * r >= MIN_LADDER_FPS - 1e-6]
