"""``upcast bench relay``: the relay's data-plane CPU per viewer, ``upcast relay``
(aioquic) against moq-dev's Rust relay core (``moq.Server``), each in its own process
under the same synthetic publisher and load-test viewers.

This package owns the benchmark (bench.py), the relay engines it starts and stops
(engines.py, with rust_relay.py as the Rust relay's process entry), the CPU/RSS probes
of a relay process (probe.py), the load-test viewers' process entry (viewers.py),
the optional py-spy profile of our relay (profile.py) and the printed table (table.py).
"""
