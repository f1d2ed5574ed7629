"""The streaming session: ring U -> encoder -> moq-lite broadcast, inputs back to the game.

May import: ``server.frames``, ``server.game`` (input events), ``server.worker`` (its
control socket), ``server.media``, ``server.moq``, ``server.quic``, ``server.ops``, the
top-level config modules, ``upscalers``. Never ``server.serve`` or the tools.
"""
