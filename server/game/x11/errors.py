"""Errors shared by the X11 modules."""

from __future__ import annotations


class DisplayError(RuntimeError):
    """An X server could not be started or reached (the message says which and how to fix it)."""


class DisplayGone(RuntimeError):
    """The X server went away while in use (killed, crashed): the session should end."""
