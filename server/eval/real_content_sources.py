"""Real content for the upscaler evaluation: pinned Debian packages and their split.

Each source is one ``.deb`` from the Debian archive (bookworm), pinned by version
and SHA-256 so that every machine unpacks the same bytes. ``pattern`` picks the
images inside the package's data tarball; its ``name`` group names an image and,
where a package ships one picture at several sizes (Plasma's wallpapers), the
``w``/``h`` groups let the largest one stand for it.

The split is per source and depends only on the image names: names are ordered by
their SHA-256 and the first quarter of them (rounded up) are held out. Networks train on the rest;
``upcast eval upscalers --real-content`` uses only held-out photographs. The
split is fixed with the pinned versions: a package with other images may move
some across, so a version bump needs a fresh split for training and evaluation.
"""

from __future__ import annotations

import hashlib
import math
import re
from dataclasses import dataclass
from pathlib import Path

DEBIAN_MIRROR = "https://deb.debian.org/debian/"
# Files Pillow cannot decode without plugins (or that are not raster images) are
# never picked: the patterns name only JPEG and PNG.
HELD_OUT_DIR = "held_out"
TRAIN_DIR = "train"


@dataclass(frozen=True)
class ContentSource:
    name: str  # folder under the content directory
    package: str
    version: str
    pool_path: str  # below DEBIAN_MIRROR
    sha256: str
    size: int  # bytes of the .deb
    kind: str  # "photograph" (evaluated) or "game" (training material, too small to crop)
    pattern: str  # regex on the tar member path (no leading "./")
    held_out_fraction: float = 0.25

    @property
    def url(self) -> str:
        return DEBIAN_MIRROR + self.pool_path


# Photographs among Plasma 5.27's wallpapers (the others are drawn or rendered art),
# chosen by looking at each once.
_PLASMA_PHOTOS = (
    "BytheWater|ColdRipple|ColorfulCups|DarkestHour|EveningGlow|FallenLeaf|Grey|Kite|"
    "OneStandsOut|Path|summer_1am"
)

# Photographs among LXQt's wallpapers (the others are drawn: origami, triangles,
# waves, logos), chosen the same way. Several are close-ups with a soft background,
# which the other two sources have few of.
_LXQT_PHOTOS = (
    "Butterfly-Kenneth-Wimer|Valendas|after-the-rain|appleflower|beam|butterfly|cloud|drop|"
    "flowers|fog|this-is-not-windows"
)

SOURCES: tuple[ContentSource, ...] = (
    ContentSource(
        name="mate-nature",
        package="mate-backgrounds",
        version="1.26.0-1",
        pool_path="pool/main/m/mate-backgrounds/mate-backgrounds_1.26.0-1_all.deb",
        sha256="7bf4c2209f34b4f61ba6d24c8b58c28b361e82e4b943aae6d42c030169af9e04",
        size=46638500,
        kind="photograph",
        pattern=r"usr/share/backgrounds/mate/nature/(?P<name>[^/]+)\.jpg",
    ),
    ContentSource(
        name="plasma-photos",
        package="plasma-workspace-wallpapers",
        version="4:5.27.5-2",
        pool_path="pool/main/p/plasma-workspace-wallpapers/"
        "plasma-workspace-wallpapers_5.27.5-2_all.deb",
        sha256="32cd18b71c8c938a18b3b351f217c02ac590e323caa3cf322fbb875ce8892f8b",
        size=94047772,
        kind="photograph",
        pattern=rf"usr/share/wallpapers/(?P<name>{_PLASMA_PHOTOS})/contents/images/"
        r"(?P<w>\d+)x(?P<h>\d+)\.(?:jpg|png)",
    ),
    ContentSource(
        name="lxqt-photos",
        package="lxqt-themes",
        version="1.2.0-1",
        pool_path="pool/main/l/lxqt-themes/lxqt-themes_1.2.0-1_all.deb",
        sha256="d518df36b515b09d36cb00b12645dd8ce170bb82bb0966297741905ce3edc8e1",
        size=25778012,
        kind="photograph",
        pattern=rf"usr/share/lxqt/wallpapers/(?P<name>{_LXQT_PHOTOS})\.(?:jpg|png)",
    ),
    ContentSource(
        # Level screenshots of Neverball (256x256 renders of its textured levels).
        name="neverball-shots",
        package="neverball-data",
        version="1.6.0+git20180603-3",
        pool_path="pool/main/n/neverball/neverball-data_1.6.0+git20180603-3_all.deb",
        sha256="08fc3a2846cab0be57235b82a6ac113ed9612ace43374b8d6ea7eed61700937f",
        size=17897156,
        kind="game",
        pattern=r"usr/share/games/neverball/shot-(?P<set>[^/]+)/(?P<name>[^/]+)\.(?:png|jpg)",
    ),
)


def source_named(name: str) -> ContentSource:
    for s in SOURCES:
        if s.name == name:
            return s
    raise KeyError(f"unknown content source {name!r}; known: {[s.name for s in SOURCES]}")


def pick_members(source: ContentSource, members: list[str]) -> dict[str, str]:
    """Image name -> tar member path: the members matching the source's pattern, the
    largest (w*h) per name where the pattern gives sizes."""
    regex = re.compile(source.pattern)
    best: dict[str, tuple[int, str]] = {}
    for member in members:
        m = regex.fullmatch(member.removeprefix("./"))
        if m is None:
            continue
        groups = m.groupdict()
        name = groups["name"] if groups.get("set") is None else f"{groups['set']}_{groups['name']}"
        area = int(groups["w"]) * int(groups["h"]) if groups.get("w") else 0
        if name not in best or area > best[name][0]:
            best[name] = (area, member)
    return {name: member for name, (_, member) in sorted(best.items())}


def split_names(names: list[str], held_out_fraction: float) -> tuple[list[str], list[str]]:
    """(train, held_out), deterministic: names ordered by SHA-256, the first
    ceil(fraction * n) held out (at least one when there are two or more)."""
    ordered = sorted(set(names), key=lambda n: hashlib.sha256(n.encode()).hexdigest())
    count = math.ceil(held_out_fraction * len(ordered))
    if len(ordered) >= 2:
        count = min(max(count, 1), len(ordered) - 1)
    return sorted(ordered[count:]), sorted(ordered[:count])


def held_out_images(content_dir: Path, kind: str = "photograph") -> list[Path]:
    """The images to evaluate under ``content_dir``, sorted so the suite's order is
    fixed: each fetched source's ``held_out`` images (of ``kind``); a folder of your
    own pictures (none of them trained on) is taken whole, its own images and those of
    each subfolder without a ``held_out`` one."""
    if not content_dir.is_dir():
        raise FileNotFoundError(
            f"content directory {content_dir} not found; fetch it with "
            f"`upcast eval content --fetch --dir {content_dir}`, or name a folder of "
            "your own pictures"
        )
    known = {s.name: s for s in SOURCES}
    found = _images_in(content_dir)
    for sub in sorted(p for p in content_dir.iterdir() if p.is_dir()):
        source = known.get(sub.name)
        if source is not None and source.kind != kind:
            continue
        held_out = sub / HELD_OUT_DIR
        found += _images_in(held_out if source is not None or held_out.is_dir() else sub)
    if not found:
        raise FileNotFoundError(
            f"no images under {content_dir} ({', '.join(sorted(IMAGE_SUFFIXES))}), in it, "
            f"in its subfolders or in their {HELD_OUT_DIR}/; fetch the project's with "
            f"`upcast eval content --fetch --dir {content_dir}`"
        )
    return found


def _images_in(folder: Path) -> list[Path]:
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())


def image_source(path: Path) -> str:
    """What an evaluated image is reported under: its fetched source (the folder above
    ``held_out``) or the folder it sits in."""
    return path.parent.parent.name if path.parent.name == HELD_OUT_DIR else path.parent.name


IMAGE_SUFFIXES = frozenset({".jpg", ".jpeg", ".png"})
