"""Operations shared by every process: logging setup and secret masking, process
liveness and stopping, CPU threads, the event loop, progress lines, browser paths,
serving Prometheus metrics, and the JSON report every benchmark and evaluation writes.

The lowest layer: imports nothing of ``server`` outside this package.
"""
