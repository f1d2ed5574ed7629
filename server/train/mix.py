"""The training mix: the game's renders plus sequences over real pictures.

``--real-content DIR`` (the folder ``upcast eval content --fetch`` fills) adds
the training pictures of every fetched source as pan/zoom/rotation sequences
(``server.train.photo_dataset``); ``share`` of the steps then draw their batch
from them: three quarters from the photographs, one quarter from Neverball's
level screenshots (rendered game content of another game), the rest from the
game's own renders. The held-out quarter of each source stays for the evaluation.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from server.train.dataset import Dataset
from server.train.loop import DataMix
from server.train.photo_dataset import (
    PHOTO_SOURCES,
    SCREENSHOT_SOURCES,
    PhotoSpec,
    PictureSource,
    load_or_generate_photos,
    training_pictures,
)

PHOTO_SEQUENCES = 192
SCREENSHOT_SEQUENCES = 96
PHOTO_PART = 0.75  # of the real-content share; the screenshots get the rest


def _pictures(content_dir: Path, sources: tuple[PictureSource, ...]) -> list[Path]:
    return [p for source in sources for p in training_pictures(content_dir, source.name)]


def build_mix(
    game: Dataset,
    content_dir: Path | None,
    share: float,
    spec: PhotoSpec,
    data_dir: Path,
) -> Dataset | DataMix:
    """``game`` alone without ``content_dir`` or with share 0, else the three-part mix.
    ``spec`` gives the frames, truth frames, scale and seed; each part its own sizes."""
    if not 0.0 <= share < 1.0:
        raise ValueError(f"the real-content share must be in [0, 1), got {share}")
    if content_dir is None or share == 0.0:
        return game
    parts: list[tuple[str, Dataset, float]] = [("game", game, 1.0 - share)]
    for label, sources, sequences, weight in (
        ("photos", PHOTO_SOURCES, PHOTO_SEQUENCES, share * PHOTO_PART),
        ("screenshots", SCREENSHOT_SOURCES, SCREENSHOT_SEQUENCES, share * (1.0 - PHOTO_PART)),
    ):
        part_spec = replace(
            spec,
            sequences=sequences,
            render_size=sources[0].render_size,
            scale_range=sources[0].scale_range,
        )
        pictures = _pictures(content_dir, sources)
        data = load_or_generate_photos(part_spec, pictures, data_dir, label)
        parts.append((label, data, weight))
    return DataMix(tuple(parts))
