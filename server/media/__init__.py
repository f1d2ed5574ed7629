"""Media encoding: x264 video encoding, CMAF (fMP4) fragments written and read, the
hang catalog that describes the tracks.

Imports nothing of ``server`` outside this package.
"""
