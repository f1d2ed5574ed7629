"""Real programs from Debian's packages to stream as source x11, for the app benchmark
and the end-to-end tests: how each is started at a given size and what a player does
with it (which keys, after which start-up key).

Each game takes its resolution its own way (SuperTux a flag, Neverball its config
file); a fresh HOME per run keeps the machine's own settings and saves out of it.
"""

from __future__ import annotations

import shlex
import shutil
from dataclasses import dataclass
from pathlib import Path

SUPERTUX = "/usr/games/supertux2"
SUPERTUX_LEVEL = "/usr/share/games/supertux2/levels/world1/welcome_antarctica.stl"
NEVERBALL = "/usr/games/neverball"


class PresetError(RuntimeError):
    """The program of a preset is not installed (the message says which package)."""


@dataclass(frozen=True)
class AppPreset:
    name: str
    package: str  # the Debian package that has the program
    program: str
    kind: str  # what it exercises
    start_keys: tuple[str, ...]  # taps after start-up (a level intro to leave)
    play_keys: tuple[str, ...]  # keys a player taps while the benchmark runs

    def command(self, size: str, home: Path) -> str:
        """The command line for ``--app`` at ``size`` (WxH), with ``home`` as HOME."""
        if shutil.which(self.program) is None:
            raise PresetError(
                f"{self.program} is missing: apt-get install --no-install-recommends {self.package}"
            )
        home.mkdir(parents=True, exist_ok=True)
        env = ["env", f"HOME={home}"]
        if self.name == "supertux":
            return shlex.join(
                [*env, self.program, "--window", "--geometry", size, "--renderer", "sdl",
                 "--disable-sound", "--disable-music", SUPERTUX_LEVEL]
            )  # fmt: skip
        width, height = size.split("x")
        config = home / ".neverball"
        config.mkdir(exist_ok=True)
        # Neverball takes its resolution from its config file only.
        (config / "neverballrc").write_text(
            f"fullscreen 0\nwidth {width}\nheight {height}\nsound_volume 0\nmusic_volume 0\n"
        )
        return shlex.join([*env, self.program])


PRESETS: dict[str, AppPreset] = {
    "supertux": AppPreset(
        "supertux",
        "supertux",
        SUPERTUX,
        "2D, SDL's renderer",
        start_keys=("Enter",),
        play_keys=("ArrowRight", "ArrowLeft", "ArrowUp"),
    ),
    "neverball": AppPreset(
        "neverball",
        "neverball",
        NEVERBALL,
        "3D, OpenGL through Mesa's llvmpipe",
        start_keys=(),
        play_keys=("ArrowDown", "ArrowUp"),
    ),
}
