"""One local game stack: the rings, the game process and the worker process (``upcast up``
and ``upcast preview``), the flags they share, the machine-fitted defaults, and the local
MJPEG preview page.

May import: ``server.frames``, ``server.game``, ``server.worker``, ``server.ops``, the
top-level config modules, ``upscalers``. Never ``server.session`` or ``server.serve``.
"""
