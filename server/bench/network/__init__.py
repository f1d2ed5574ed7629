"""``upcast bench network`` and ``upcast bench congestion``: play over emulated real
links, and QUIC congestion controllers carrying video through lossy ones."""
