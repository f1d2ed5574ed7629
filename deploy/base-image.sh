#!/usr/bin/env bash
# Makes the offline base image: Debian bookworm (minbase) with Python 3.11 and venv,
# from a Debian package mirror, without any image registry:
#
#   deploy/base-image.sh [TAG]        (default upcast/base:bookworm-py3.11)
#
# debootstrap writes a root file system that `docker import` turns into an image; the
# Dockerfiles take it with --build-arg BASE_IMAGE=TAG in place of python:3.11-slim-bookworm
# (both have python3 with venv: the images install into /opt/venv either way).
# The mirror is the one apt on this machine uses (UPCAST_DEBIAN_MIRROR overrides it).
# Needs root, debootstrap and a running dockerd. Does nothing when TAG exists.
set -euo pipefail

tag="${1:-upcast/base:bookworm-py3.11}"
if docker image inspect "$tag" >/dev/null 2>&1; then
    echo "base image: $tag already there"
    exit 0
fi
command -v debootstrap >/dev/null || {
    echo "base image: debootstrap is missing (Debian: apt-get install debootstrap)" >&2
    exit 1
}

mirror_of_apt() {
    # deb822 sources (bookworm's default) first, then the one-line format.
    local uri
    uri=$(awk '/^URIs:/ {print $2; exit}' /etc/apt/sources.list.d/*.sources 2>/dev/null || true)
    if [ -z "$uri" ]; then
        uri=$(awk '$1 == "deb" && $2 !~ /^\[/ {print $2; exit} $1 == "deb" {print $3; exit}' \
            /etc/apt/sources.list 2>/dev/null || true)
    fi
    echo "${uri:-http://deb.debian.org/debian}"
}
mirror="${UPCAST_DEBIAN_MIRROR:-$(mirror_of_apt)}"

root=$(mktemp -d /var/tmp/upcast-base.XXXXXX)
trap 'rm -rf "$root"' EXIT
echo "base image: debootstrap bookworm from $mirror (a few minutes) ..."
t0=$SECONDS
# python3-venv: the images make /opt/venv (pip is in the venv, from ensurepip);
# ca-certificates for anything that fetches over TLS at run time.
debootstrap --variant=minbase --include=python3,python3-venv,ca-certificates \
    bookworm "$root" "$mirror" >/dev/null
# Only what the images need: no apt lists, caches or docs.
rm -rf "$root"/var/lib/apt/lists/* "$root"/var/cache/apt/*.bin "$root"/usr/share/doc/* \
    "$root"/usr/share/man/*
tar -C "$root" -c . | docker import \
    --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
    --change 'ENV LANG=C.UTF-8' \
    --change 'CMD ["/bin/bash"]' \
    - "$tag" >/dev/null
echo "base image: $tag made in $((SECONDS - t0)) s," \
    "$(docker image inspect -f '{{.Size}}' "$tag" | awk '{printf "%.0f MB", $1 / 1e6}')"
