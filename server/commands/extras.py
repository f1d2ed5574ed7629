"""What a command on the base install says when it needs the extra ``game``.

The base install (pyproject.toml) runs the relay side only; a game command on it
fails at its first import of one of the extra's packages. ``server.cli`` turns
that ModuleNotFoundError into one line naming the extra instead of a traceback.
"""

from __future__ import annotations

EXTRA = "game"
INSTALL = f"pip install 'upcast[{EXTRA}]'"

# Import name -> its distribution in [project.optional-dependencies] game
# (tests/test_base_install.py checks the two lists agree).
GAME_MODULES: dict[str, str] = {
    "torch": "torch",
    "numba": "numba",
    "PIL": "pillow",
    "skimage": "scikit-image",
    "flip_evaluator": "flip-evaluator",
    "matplotlib": "matplotlib",
    "cv2": "opencv-python-headless",
    "mss": "mss",
    "Xlib": "python-xlib",
}


def missing_extra(exc: ModuleNotFoundError, who: str) -> str | None:
    """The message (from ``who``, e.g. ``upcast up``) for ``exc`` if a package of the
    extra is what is missing, else None."""
    distribution = GAME_MODULES.get((exc.name or "").partition(".")[0])
    if distribution is None:
        return None
    return (
        f"{who}: needs the extra {EXTRA!r} ({distribution} is not installed; "
        f"this is the base install, which runs relay, token, control and loadtest): {INSTALL}"
    )
