#!/usr/bin/env bash
# The Debian package as a user gets it: built by deploy/package (fast compression, and the
# dev-profile binary the test build left, to keep CI short: building `-p xrce-agent` alone
# resolves the dependencies' features apart from the whole workspace's and rebuilt the Zenoh
# stack, 2.5 minutes; that binary also carries the tests' inert fault-injection hooks; users
# build the release one), installed with dpkg,
# then checked from where it installed: `xrce-agent --version` from /usr/bin, the man page,
# the xrce-agent user and its home, the conffile, `systemd-analyze verify` on every
# installed unit (template units through an instance), and removed and purged again.
# Needs root or sudo (dpkg). Refuses to run where xrce-agent is installed already (it would
# remove it). What stays after it: the xrce-agent user and its empty home (Debian keeps
# system users), and Debian's systemd package if this script installed it.
set -euo pipefail
cd "$(dirname "$0")/.."

sudo=""
if [ "$(id -u)" -ne 0 ]; then
    sudo="sudo"
fi
fail() { echo "package-check: $*" >&2; exit 1; }

# systemd-analyze and systemd-sysusers (Debian's systemd package; a container may lack it).
if ! command -v systemd-analyze >/dev/null 2>&1; then
    $sudo apt-get update -qq
    $sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends systemd >&2
fi

if dpkg -s xrce-agent >/dev/null 2>&1; then
    fail "xrce-agent is already installed here; remove it first"
fi
# The test build's binaries, as the test harness makes them (a no-op after `cargo test
# --workspace`, and never a stale binary when run on its own).
cargo test --workspace --locked --no-run --quiet
deploy/package --profile dev --fast --prebuilt
deb=$(ls -t "${CARGO_TARGET_DIR:-target}"/debian/xrce-agent_*.deb | head -1)
echo "package-check: installing $deb"
cleanup() { $sudo dpkg -P xrce-agent >/dev/null 2>&1 || true; }
trap cleanup EXIT
$sudo dpkg -i "$deb"

version=$(/usr/bin/xrce-agent --version)
echo "$version"
grep -q '^commit: ' <<<"$version" || fail "--version names no commit"
grep -q '^DDS backends: cyclone' <<<"$version" || fail "--version names no Cyclone DDS backend"
[ -f /usr/share/man/man1/xrce-agent.1.gz ] || fail "no man page"
[ -f /usr/share/bash-completion/completions/xrce-agent ] || fail "no bash completion"
for doc in README.md BENCHMARKS.md docs/cli.md docs/gateway.md docs/usage.md docs/operations.md; do
    [ -f "/usr/share/doc/xrce-agent/$doc" ] || fail "no /usr/share/doc/xrce-agent/$doc (the README links to it)"
done
grep -qx '/etc/xrce-agent/gateway.toml' /var/lib/dpkg/info/xrce-agent.conffiles \
    || fail "the gateway file is not a conffile"
/usr/bin/xrce-agent --config /etc/xrce-agent/gateway.toml --check >/dev/null \
    || fail "the installed gateway file does not check"
getent passwd xrce-agent >/dev/null || fail "no xrce-agent user (sysusers)"
[ "$(stat -c '%U %a' /var/lib/xrce-agent)" = "xrce-agent 700" ] || fail "/var/lib/xrce-agent not private to xrce-agent (tmpfiles)"

units=0
for path in /lib/systemd/system/xrce-*.service; do
    unit=$(basename "$path")
    case "$unit" in
        *@.service) unit="${unit%@.service}@instance1.service" ;;
    esac
    systemd-analyze verify "/lib/systemd/system/$unit" || fail "systemd-analyze verify $unit"
    units=$((units + 1))
done
[ "$units" -ge 6 ] || fail "only $units units installed"
echo "package-check: $units units verified"

$sudo dpkg -r xrce-agent
[ ! -e /usr/bin/xrce-agent ] || fail "the binary stayed after removal"
[ -f /etc/xrce-agent/gateway.toml ] || fail "the conffile went with dpkg -r (it goes with --purge)"
$sudo dpkg -P xrce-agent
[ ! -e /etc/xrce-agent/gateway.toml ] || fail "the conffile stayed after purge"
trap - EXIT
echo "package-check: the package installs, checks and removes cleanly"
