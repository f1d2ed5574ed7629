"""The moq-lite relay process: its QUIC/WebTransport server, its settings, and running it
as a child process (``upcast up``, ``upcast serve``).

May import: ``server.moq``, ``server.quic``, ``server.auth``, ``server.frames`` (the monitor),
``server.ops``. Never a session, the game or the worker.
"""
