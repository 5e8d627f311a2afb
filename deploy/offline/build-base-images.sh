#!/usr/bin/env bash
# Offline stand-ins for the two upstream images of deploy/ (python:3.11-slim and postgres:17-alpine), built from
# Debian's own packages where no image registry is reachable. They are test images, named so:
#   radarseg-test/debian:bookworm     debootstrap --variant=minbase bookworm, imported with `docker import`
#   radarseg-test/python:3.11         + Debian's python3.11, python3.11-venv, python3-pip
#   radarseg-test/postgres:15         + Debian's postgresql (15), with the official image's POSTGRES_* variables
# Each image also trusts this machine's CA bundle (/etc/ssl/certs/ca-certificates.crt, copied in as
# /etc/ssl/certs/host-ca-bundle.crt), so that pip inside a build reaches the package index the host reaches.
# The debootstrap image is kept once made (build once, reuse; --rebuild makes it again); the other two are
# built every time, from Docker's layer cache when their folders did not change (seconds).
# Needs: root, docker (a running engine), debootstrap, and a Debian mirror (DEBIAN_MIRROR) on the network.
#   deploy/offline/build-base-images.sh            # then: deploy/offline/README.md for the build with them
set -euo pipefail
cd "$(dirname "$0")"

DEBIAN_IMAGE=radarseg-test/debian:bookworm
PYTHON_IMAGE=radarseg-test/python:3.11
POSTGRES_IMAGE=radarseg-test/postgres:15
DEBIAN_MIRROR="${DEBIAN_MIRROR:-http://deb.debian.org/debian}"
HOST_CA_BUNDLE="${HOST_CA_BUNDLE:-/etc/ssl/certs/ca-certificates.crt}"
REBUILD=0
[ "${1:-}" = "--rebuild" ] && REBUILD=1

have() { [ "$REBUILD" = 0 ] && docker image inspect "$1" >/dev/null 2>&1; }

if have "$DEBIAN_IMAGE"; then
    echo "kept $DEBIAN_IMAGE"
else
    rootfs="$(mktemp -d /tmp/radarseg-rootfs.XXXXXX)"
    trap 'rm -rf "$rootfs"' EXIT
    echo "debootstrap bookworm (minbase) into $rootfs from $DEBIAN_MIRROR"
    debootstrap --variant=minbase --include=ca-certificates bookworm "$rootfs" "$DEBIAN_MIRROR" >"$rootfs.log" 2>&1 \
        || { tail -20 "$rootfs.log"; exit 1; }
    rm -f "$rootfs.log"
    cp "$HOST_CA_BUNDLE" "$rootfs/etc/ssl/certs/host-ca-bundle.crt"
    printf 'deb %s bookworm main\n' "$DEBIAN_MIRROR" >"$rootfs/etc/apt/sources.list"
    rm -rf "$rootfs"/var/cache/apt/archives/*.deb "$rootfs"/var/lib/apt/lists/*
    tar -C "$rootfs" -c . | docker import \
        --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
        --change 'ENV SSL_CERT_FILE=/etc/ssl/certs/host-ca-bundle.crt' \
        --change 'ENV PIP_CERT=/etc/ssl/certs/host-ca-bundle.crt' \
        --change 'LABEL org.opencontainers.image.description="radarseg test image: Debian bookworm minbase"' \
        --change 'CMD ["bash"]' - "$DEBIAN_IMAGE"
    rm -rf "$rootfs"
    trap - EXIT
fi

for spec in "python:$PYTHON_IMAGE" "postgres:$POSTGRES_IMAGE"; do
    folder="${spec%%:*}" image="${spec#*:}"
    docker build -q --build-arg BASE_IMAGE="$DEBIAN_IMAGE" -t "$image" "$folder" >/dev/null
done
docker image ls --format '{{.Repository}}:{{.Tag}} {{.Size}}' | grep '^radarseg-test/'
