"""``upcast bench``: the benchmarks that write the JSON reports of DESIGN.md.

A tool: may import any stage, ``server.serve``, ``server.loadtest`` and ``upscalers``; no
stage imports it. One package per family with more than one module (``adversary/``,
``network/``, ``app/``, ``reframe/``, ``adaptive/``: each has its ``bench.py``, the
command), the single-module benchmarks beside them; ``server.commands.bench`` maps the
names to modules.
"""
