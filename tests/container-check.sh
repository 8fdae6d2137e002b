#!/usr/bin/env bash
# The container recipe (deploy/Containerfile) built and run with buildah, a daemonless
# builder from Debian's packages. No container registry is reachable from CI, so neither the
# recipe's base images (rust, debian:bookworm-slim) can be pulled: this builds the recipe's
# runtime stage, as written, on a Debian bookworm base made here with debootstrap, with the
# binary the package check built in place of the build stage's (which needs the rust image),
# then runs the image: --version, the non-root user in dialout, and an agent that gets ready
# (UDP and DDS on loopback). Where buildah cannot make containers (no privileges), it says
# so and stops without failing; a wrong image fails.
set -euo pipefail
cd "$(dirname "$0")/.."

sudo=""
if [ "$(id -u)" -ne 0 ]; then
    sudo="sudo"
fi
fail() { echo "container-check: $*" >&2; exit 1; }
skip() { echo "container-check: SKIPPED, $*" >&2; exit 0; }

missing=()
command -v buildah >/dev/null 2>&1 || missing+=(buildah)
command -v debootstrap >/dev/null 2>&1 || missing+=(debootstrap)
if [ ${#missing[@]} -gt 0 ]; then
    $sudo apt-get update -qq
    $sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
        "${missing[@]}" >&2 || skip "could not install ${missing[*]}"
fi
B=($sudo buildah --storage-driver vfs)

target="${CARGO_TARGET_DIR:-target}"
bin="$target/release/package/xrce-agent"   # staged by deploy/package (tests/package-check.sh)
[ -x "$bin" ] || fail "no $bin: run deploy/package first"

work="$target/container-check"
rootfs="$work/rootfs"
if [ ! -x "$rootfs/bin/sh" ]; then
    rm -rf "$rootfs"
    mkdir -p "$work"
    $sudo debootstrap --variant=minbase bookworm "$rootfs" http://deb.debian.org/debian >/dev/null \
        || skip "debootstrap could not make a Debian base"
fi

base=localhost/xrce-agent-check-base
image=localhost/xrce-agent-check
containers=()
cleanup() {
    for c in "${containers[@]}"; do "${B[@]}" rm "$c" >/dev/null 2>&1 || true; done
    "${B[@]}" rmi -f "$image" "$base" >/dev/null 2>&1 || true
}
trap cleanup EXIT

scratch=$("${B[@]}" from scratch 2>/dev/null) || skip "buildah cannot make a container here"
containers+=("$scratch")
"${B[@]}" copy "$scratch" "$rootfs" / >/dev/null
"${B[@]}" commit -q "$scratch" "$base" >/dev/null
# Whether buildah can run a command in a container here (the recipe's RUN needs it).
probe=$("${B[@]}" from -q "$base")
containers+=("$probe")
"${B[@]}" run --isolation chroot "$probe" -- true >/dev/null 2>&1 \
    || skip "buildah cannot run a command in a container here"

# The recipe's runtime stage, as written, but for where its binary comes from.
ctx="$work/context"
rm -rf "$ctx"
mkdir -p "$ctx/deploy"
strip -o "$ctx/xrce-agent" "$bin"
cp deploy/gateway.example.toml "$ctx/deploy/"
{
    echo "ARG RUNTIME_IMAGE=$base"
    sed -n '/^FROM \${RUNTIME_IMAGE}$/,$p' deploy/Containerfile \
        | sed 's#^COPY --from=build /src/target/release/xrce-agent #COPY xrce-agent #'
} > "$ctx/Containerfile"
grep -q '^COPY xrce-agent /usr/bin/xrce-agent$' "$ctx/Containerfile" \
    || fail "the recipe's runtime stage no longer copies the binary as this check expects"
"${B[@]}" bud -q --isolation chroot -t "$image" -f "$ctx/Containerfile" "$ctx" >/dev/null \
    || fail "the runtime stage does not build"

run=$("${B[@]}" from -q "$image")
containers+=("$run")
R=("${B[@]}" run --isolation chroot "$run" --)
"${R[@]}" /usr/bin/xrce-agent --version | grep -q '^DDS backends: cyclone' \
    || fail "--version in the image names no Cyclone DDS backend"
user=$("${R[@]}" id)
echo "container-check: runs as $user"
case "$user" in
    uid=0*) fail "the image runs as root" ;;
esac
grep -q '(dialout)' <<<"$user" || fail "the image's user is not in dialout"
out=$("${R[@]}" sh -c 'timeout -s INT 8 /usr/bin/xrce-agent udp4 -p 18888 --bind 127.0.0.1 --dds-interface 127.0.0.1 2>&1; rm -rf "/dev/shm/xrce-agent-$(id -u)"' || true)
grep -q 'agent ready' <<<"$out" || { echo "$out" | tail -20 >&2; fail "the agent in the image never got ready"; }
echo "container-check: the recipe's runtime stage builds, runs as a non-root user and serves"
