"""``upcast bench``: the benchmarks that write the JSON reports of DESIGN.md.

A tool: may import any stage and ``upscalers``; no stage imports it.
"""
