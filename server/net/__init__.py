"""User-space network emulation (issue 21): shaped UDP between viewers and the relay.

``link_profile`` says what a link does, ``profiles`` names the issue's links and
reads schedule files, ``shaper`` decides each packet's fate without sockets, and
``emulator`` is the asyncio UDP proxy that applies it on loopback.
"""

from server.net.emulator import EmulatorThread, NetworkEmulator, NonLoopbackError, emulator_loop
from server.net.link_profile import Direction, GilbertElliott, LinkProfile, Schedule, Step
from server.net.profiles import PROFILES, ProfileError, load_schedule, resolve
from server.net.shaper import Decision, DirectionShaper, Fate, LinkShaper

__all__ = [
    "PROFILES",
    "Decision",
    "Direction",
    "DirectionShaper",
    "EmulatorThread",
    "Fate",
    "GilbertElliott",
    "LinkProfile",
    "LinkShaper",
    "NetworkEmulator",
    "NonLoopbackError",
    "ProfileError",
    "Schedule",
    "Step",
    "emulator_loop",
    "load_schedule",
    "resolve",
]
