"""``upcast loadtest``: many moq-lite viewers against a relay, measured.

A tool: may import any stage (``server.moq``, ``server.quic``, ``server.session``,
``server.media``, ...) and ``server.ops.report``; no stage imports it, nor does it import
``server.bench`` (which uses its viewers).
"""
