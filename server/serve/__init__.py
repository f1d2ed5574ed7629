"""``upcast serve``: many game sessions on one host, each in its own process, one relay.

May import: every stage below it (``server.session``, ``server.stack``, ``server.relay``,
``server.quic``, ``server.moq``, ``server.auth``, ``server.frames``, ``server.ops``), the
top-level config modules. Never the tools or ``server.commands``.
"""
