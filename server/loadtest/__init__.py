"""``upcast loadtest``: many moq-lite viewers against a relay, measured.

A tool: may import any stage (``server.moq``, ``server.quic``, ``server.session``,
``server.media``, ...) and ``server.bench``'s report helpers; no stage imports it.
"""
