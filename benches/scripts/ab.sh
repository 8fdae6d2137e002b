#!/bin/sh
# The headline benchmarks, one build (or agent) against another, alternating round by round
# (xrce-loadgen --compare-with), 3 rounds each, medians; one output file per case under a
# dated folder of benches/results/. DDS and every socket stay on loopback: run it in a network
# namespace with only loopback (it enters one itself with `unshare -rn` when it can).
#
#   benches/scripts/ab.sh NEW_AGENT OLD_AGENT [CASE...]
#   OLD_CMD='MicroXRCEAgent udp4 -p {port}' benches/scripts/ab.sh NEW_AGENT [CASE...]
#
# NEW_AGENT and OLD_AGENT are `xrce-agent` executables (release builds copied aside), or, for
# a reference such as MicroXRCEAgent, set OLD_CMD to its whole command line with `{port}`
# where the port goes and leave OLD_AGENT out (paths without spaces). LOADGEN names
# xrce-loadgen (default: the release build of this tree), OUT the folder (default
# benches/results/<today>), ROUNDS the rounds per case (3).
#
# Cases (default: latency-10k clients-10-1k clients-100-20k):
#   latency-1k            1 -> 1 best-effort at 1,000/s (p50 / p99)
#   latency-10k           1 -> 1 best-effort at 10,000/s
#   clients-10-1k         10 clients -> 1 at 1,000/s in all (CPU per sample)
#   clients-100-10k       100 clients -> 1 at 10,000/s
#   clients-100-20k       100 clients -> 1 at 20,000/s
#   clients-100-60k       100 clients -> 1 at 60,000/s
#   clients-100-reliable  100 reliable clients -> 1 at 20,000/s
#   clients-1000-20k      1,000 clients -> 1 at 20,000/s
#   clients-100-unlimited 100 reliable clients -> 1 as fast as their windows allow (into DDS)
#   kill-soak             each agent alone (not alternated): 100 reliable clients -> 1 at
#                         1,000/s, worker and front-end SIGKILLed in turn every 6 s, 14 kills
#                         (lost / repeated); with OLD_CMD (no worker to kill), NEW only
set -eu
here=$(cd "$(dirname "$0")/../.." && pwd)
if [ "${XRCE_AB_IN_NETNS:-}" != 1 ]; then
  if command -v unshare >/dev/null 2>&1 && unshare -rn true 2>/dev/null; then
    export XRCE_AB_IN_NETNS=1
    exec unshare -rn sh -c 'ip link set lo up && exec sh "$0" "$@"' "$0" "$@"
  fi
  echo "ab.sh: cannot enter a network namespace (unshare -rn): DDS would reach every" \
    "interface; as root: unshare -n sh -c 'ip link set lo up; XRCE_AB_IN_NETNS=1 sh $0 ...'" >&2
  exit 1
fi
if [ -n "${OLD_CMD:-}" ]; then
  [ $# -ge 1 ] || { sed -n '2,28p' "$0"; exit 2; }
  NEW=$1
  OLD=
  shift
else
  [ $# -ge 2 ] || { sed -n '2,28p' "$0"; exit 2; }
  NEW=$1
  OLD=$2
  shift 2
fi
# Inside the namespace this user is root: the agents' private runtime directory goes in a
# fresh temporary one, never root's own.
XRCE_RUNTIME_DIR=${XRCE_RUNTIME_DIR:-$(mktemp -d)}
export XRCE_RUNTIME_DIR
L=${LOADGEN:-$here/target/release/xrce-loadgen}
O=${OUT:-$here/benches/results/$(date +%F)}
R=${ROUNDS:-3}
mkdir -p "$O"
# Each round starts a fresh agent on the same port: without this it would take the sessions
# the previous round stored over (what a restarted agent does), which no benchmark wants.
export XRCE_DISCARD_SESSIONS=true
C="udp4 -p {port} --dds-interface 127.0.0.1 -v 2"
A="$NEW $C"
B=${OLD_CMD:-"$OLD $C"}
run() {
  name=$1
  shift
  echo "== $name: $*" | tee "$O/ab-$name.txt"
  "$L" "$@" --payload 40 --rounds "$R" --agent-cmd "$A" --compare-with "$B" \
    >>"$O/ab-$name.txt" 2>&1
}
soak() {
  builds="new old"
  [ -z "${OLD_CMD:-}" ] || builds=new
  for which in $builds; do
    if [ $which = new ]; then agent=$A; else agent=$B; fi
    echo "== kill-soak ($which): $agent" | tee "$O/kill-soak-$which.txt"
    "$L" --publishers 100 --subscribers 1 --rate 1000 --samples 100000 --duration 110 \
      --kills 14 --kill alternate --kill-every 6 --agent-cmd "$agent" \
      >>"$O/kill-soak-$which.txt" 2>&1
  done
}
[ $# -gt 0 ] || set -- latency-10k clients-10-1k clients-100-20k
for case in "$@"; do
  case $case in
    latency-1k) run "$case" --publishers 1 --subscribers 1 --rate 1000 --best-effort --samples 20000 ;;
    latency-10k) run "$case" --publishers 1 --subscribers 1 --rate 10000 --best-effort --samples 100000 ;;
    clients-10-1k) run "$case" --publishers 10 --subscribers 1 --rate 1000 --best-effort --samples 20000 ;;
    clients-100-10k) run "$case" --publishers 100 --subscribers 1 --rate 10000 --best-effort --samples 100000 ;;
    clients-100-20k) run "$case" --publishers 100 --subscribers 1 --rate 20000 --best-effort --samples 200000 ;;
    clients-100-60k) run "$case" --publishers 100 --subscribers 1 --rate 60000 --best-effort --samples 600000 ;;
    clients-100-reliable) run "$case" --publishers 100 --subscribers 1 --rate 20000 --samples 200000 ;;
    clients-1000-20k) run "$case" --publishers 1000 --subscribers 1 --rate 20000 --best-effort --samples 200000 ;;
    clients-100-unlimited) run "$case" --publishers 100 --subscribers 1 --samples 400000 --duration 30 ;;
    kill-soak) soak ;;
    *) echo "unknown case $case" >&2; exit 2 ;;
  esac
done
echo "outputs in $O"
