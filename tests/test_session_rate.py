"""SessionRate: the controller's decisions reach the encoder, the frame rate gives way last."""

from __future__ import annotations

import time

import numpy as np

from server.media.encode import MIN_BITRATE, EncoderConfig, VideoEncoder
from server.session.feedback import FeedbackFields
from server.session.link_probe import MAX_PROBE_S
from server.session.session_rate import MIN_BITS_PER_PIXEL, RESTORE_FACTOR, SessionRate
from server.session.viewer_input import FeedbackMessage, KeysMessage

W, H, FPS = 320, 180, 30
FLOOR = MIN_BITS_PER_PIXEL * W * H * FPS  # 60 kbit/s: below it, every other frame


def make(bitrate: int = 1_000_000) -> tuple[SessionRate, dict[str, str | float | bool]]:
    state: dict[str, str | float | bool] = {}
    encoder = VideoEncoder(EncoderConfig(W, H, fps=FPS, bitrate=bitrate))
    return SessionRate(encoder, state), state


def feedback(**fields: object) -> FeedbackMessage:
    return FeedbackMessage.model_validate({"type": "feedback", **fields})


def test_the_configured_rate_stands_without_players_and_is_published() -> None:
    rate, state = make()
    rate.step(1.0)
    assert state["bitrate"] == 1_000_000
    assert state["rate_reason"] == "configured"
    assert state["fps_divisor"] == 1


def test_an_old_page_without_feedback_gets_the_safe_rate() -> None:
    rate, state = make()
    rate.on_message("page", KeysMessage(type="keys", down=["w"]))
    rate.step(rate.controller._players["page"].first_seen_s + 3.5)
    assert state["bitrate"] == 250_000
    assert state["rate_reason"] == "no feedback"
    assert rate.encoder.bitrate == 250_000


def test_a_rate_too_low_for_the_frame_rate_halves_it_and_restores_it() -> None:
    rate, state = make(bitrate=200_000)
    controller = rate.controller
    controller.floor = 10_000
    # The controller decides 50 kbit/s (below the floor of 60): every other frame,
    # and x264 (which budgets per frame at 30 fps) is told twice that.
    controller.ceiling = 50_000
    controller.input_seen("page", 0.0)
    controller.feedback("page", FeedbackFields(player=True), 0.0)
    controller._players["page"].rate = 50_000
    rate.step(0.5)
    assert rate.frame_divisor == 2
    assert rate.encoder.bitrate == 100_000
    assert state["fps_divisor"] == 2 and state["bitrate"] == 50_000
    # Just above the floor: stays halved (hysteresis); well above: every frame again.
    controller._players["page"].rate = FLOOR * 1.2
    controller.feedback("page", FeedbackFields(player=True), 0.9)
    controller.ceiling = 200_000
    rate.step(1.0)
    assert rate.frame_divisor == 2
    controller._players["page"].rate = FLOOR * RESTORE_FACTOR + 1000
    controller.feedback("page", FeedbackFields(player=True), 1.4)
    rate.step(1.5)
    assert rate.frame_divisor == 1
    assert rate.encoder.bitrate == max(MIN_BITRATE, int(FLOOR * RESTORE_FACTOR + 1000))


def test_rate_control_off_keeps_the_configured_bitrate() -> None:
    state: dict[str, str | float | bool] = {}
    encoder = VideoEncoder(EncoderConfig(W, H, fps=FPS, bitrate=1_000_000))
    rate = SessionRate(encoder, state, enabled=False)
    rate.on_message("page", feedback(player=True))
    rate.step(10.0)
    assert encoder.bitrate == 1_000_000
    assert state["rate_reason"] == "fixed"


def test_a_configured_rate_below_the_encoder_floor_still_works() -> None:
    state: dict[str, str | float | bool] = {}
    encoder = VideoEncoder(EncoderConfig(W, H, fps=FPS, bitrate=60_000))
    rate = SessionRate(encoder, state)
    rate.on_message("page", KeysMessage(type="keys", down=[]))
    rate.step(100.0)
    assert encoder.bitrate <= 60_000


def test_the_rate_is_on_the_sessions_metrics() -> None:
    from prometheus_client import CollectorRegistry

    registry = CollectorRegistry()
    encoder = VideoEncoder(EncoderConfig(W, H, fps=FPS, bitrate=1_000_000))
    rate = SessionRate(encoder, {}, registry=registry)
    rate.on_message("page", KeysMessage(type="keys", down=[]))
    rate.step(rate.controller._players["page"].first_seen_s + 3.5)
    assert registry.get_sample_value("upcast_video_bitrate_bps") == 250_000
    assert registry.get_sample_value("upcast_fps_divisor") == 1
    assert registry.get_sample_value("upcast_bitrate_changes_total") == 1


def test_a_probe_pads_the_encoders_frames_for_its_duration_and_no_longer() -> None:
    rate, state = make(bitrate=3_000_000)
    controller = rate.controller
    now = time.monotonic()  # frame_sent stamps frames on the monotonic clock
    controller.input_seen("page", now)
    target = controller.probe.start(1_000_000, controller.ceiling, ["page"], now)
    rate.step(now)
    assert state["probe_bps"] == round(target) == 1_250_000
    pixels = np.full((H, W, 3), 128, np.uint8)  # a flat frame: x264 needs a few bytes
    encoded = rate.encoder.encode(pixels, frame_id=1, pts_us=1)
    # 1.25 Mbit/s over a 30 fps frame interval: 5208 bytes on the wire for this frame.
    assert len(encoded.fragment) == encoded.padded_to == int(target / 8 / FPS)
    assert encoded.filler_bytes > 4000
    rate.frame_sent(encoded)
    probe = controller.probe.current
    assert probe is not None and list(probe.frames) == [1]  # the probe times this frame
    # Past the probe's end (here, short of frames, its longest) the padding stops.
    rate.step(now + MAX_PROBE_S + 0.01)
    assert state["probe_bps"] == 0
    after = rate.encoder.encode(pixels, frame_id=2, pts_us=2)
    assert after.padded_to == 0 and after.filler_bytes == 0


def test_a_lower_source_rate_keeps_the_bits_per_second_and_thins_no_further() -> None:
    """The game's frame rate was halved (adaptive quality): x264, which budgets per frame
    at its configured 30 fps, is told twice the rate so each frame gets twice the bits;
    and the bits-per-pixel floor is the halved rate's, so the link does not halve it
    again for a rate that now carries it."""
    rate, state = make(bitrate=200_000)
    controller = rate.controller
    controller.floor = 10_000
    controller.input_seen("page", 0.0)
    controller.feedback("page", FeedbackFields(player=True), 0.0)
    controller._players["page"].rate = 50_000  # under the 30 fps floor (60k), over 15's
    rate.set_source_fps(15.0)
    rate.step(0.5)
    assert rate.frame_divisor == 1
    assert rate.encoder.bitrate == 100_000
    assert state["bitrate"] == 50_000
    # Below 20 fps the stream is never thinned further, however narrow the link.
    controller._players["page"].rate = 12_000
    controller.feedback("page", FeedbackFields(player=True), 0.9)
    rate.step(1.0)
    assert rate.frame_divisor == 1
