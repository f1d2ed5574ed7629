"""Send one control request to a session over MoQ and wait for its result.

The request goes where a browser's controls send theirs: a broadcast
``<broadcast>/input/control-<id>`` with an ``input`` track holding one
``control`` frame. The session answers on its ``status`` track; the result
is the first status record whose ``last_control`` carries our seq and path.
"""

from __future__ import annotations

import asyncio
import json
import logging
import secrets
import uuid

from pydantic import ValidationError

from server.moq.events import Event, FrameReceived, SubscribeClosed, SubscribeRequested
from server.moq.session import SessionClosedError
from server.ops.redact import redact_url
from server.quic.client import WtConnectError
from server.quic.moq_link import MoqLink, connect_moq
from server.session.session_control import STATUS_TRACK, SessionControl, StatusRecord

log = logging.getLogger(__name__)

INPUT_TRACK = "input"


class ControlError(RuntimeError):
    """No answer: the relay is unreachable, the broadcast unknown, or the session silent."""


async def request_control(
    relay_url: str,
    broadcast: str,
    control: SessionControl | dict[str, object],
    *,
    cert_hash_hex: str | None = None,
    timeout_s: float = 15.0,
) -> StatusRecord:
    """The status record that answers the request (its ``last_control`` is our result).

    ``control`` may be a dict so a caller can send what the session must refuse."""
    seq = secrets.randbelow((1 << 53) - 1) + 1
    # A dict goes out as it is, unvalidated: the session must answer bad requests too.
    fields = control.requested() if isinstance(control, SessionControl) else dict(control)
    wire = json.dumps({"type": "control", "seq": seq, **fields}).encode()
    source = f"{broadcast.strip('/')}/input/control-{uuid.uuid4().hex[:8]}"
    answer: asyncio.Future[StatusRecord] = asyncio.get_running_loop().create_future()
    status_sub: list[int] = []
    sent: list[bool] = []

    def on_events(link: MoqLink, events: list[Event]) -> None:
        for e in events:
            if isinstance(e, SubscribeRequested):
                _answer_subscribe(link, e)
            elif isinstance(e, FrameReceived) and e.subscription_id in status_sub:
                _on_status(e.payload)
            elif (
                isinstance(e, SubscribeClosed) and e.subscription_id in status_sub
            ) and not answer.done():
                answer.set_exception(
                    ControlError(f"broadcast {broadcast!r} has no status track on the relay")
                )
        link.flush()

    def _answer_subscribe(link: MoqLink, e: SubscribeRequested) -> None:
        moq = link.moq
        if e.broadcast.strip("/") != source or e.track != INPUT_TRACK:
            moq.reject_subscribe(e.request_id)
            return
        if not moq.accept_subscribe(e.request_id):
            return
        stream = moq.open_group(e.request_id, len(sent))
        if stream is not None:
            moq.write_frame(stream, wire)
            moq.finish_group(stream)
            sent.append(True)
            log.info("control request %d sent as %s", seq, source)

    def _on_status(data: bytes) -> None:
        try:
            record = StatusRecord.model_validate_json(data)
        except ValidationError:
            return
        last = record.last_control
        if last is not None and last.seq == seq and last.source == source and not answer.done():
            answer.set_result(record)

    try:
        link = await connect_moq(
            relay_url, on_events=on_events, cert_hash_hex=cert_hash_hex, timeout=timeout_s
        )
    except (WtConnectError, OSError, TimeoutError, ValueError) as exc:
        raise ControlError(f"relay {redact_url(relay_url)} unreachable: {exc}") from None
    try:
        link.moq.publish(source)
        status_sub.append(link.moq.subscribe(broadcast, STATUS_TRACK))
        link.flush()
        try:
            async with asyncio.timeout(timeout_s):
                return await answer
        except TimeoutError:
            what = "never asked for the request" if not sent else "did not answer"
            raise ControlError(f"session {broadcast!r} {what} within {timeout_s:.0f} s") from None
    except SessionClosedError as exc:
        raise ControlError(f"relay closed the session: {exc}") from None
    finally:
        if not link.closed:
            link.wt.close(0, "control request done")
