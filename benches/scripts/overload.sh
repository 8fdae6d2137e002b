#!/bin/sh
# Overload: 100 clients flood an agent with best-effort 1 kB samples while one reliable
# client pair (another DDS domain, other client keys) publishes and reads 1,000 samples/s;
# reports the quiet pair's delivery and latency, the flood's, the agent's peak RSS (all its
# processes), its drop counters and the kernel's UDP counters.
#
#   unshare -n sh -c 'ip link set lo up; benches/scripts/overload.sh TAG [AGENT COMMAND...]'
#
# The agent must listen on UDP 9000 with its metrics on 127.0.0.1:9100 (default command
# below). FLOOD_RATE (samples/s in total, 0 = as fast as the generator can), QUIET_PORT
# (another front-end of a gateway), QUIET_DELAY (seconds from the flood's start to the quiet
# pair's: the flood sends only once its writers matched, which takes the reference agent
# about a minute), QUIET_ARGS (more load generator options for the quiet pair, such as
# `--best-effort`), OUT (result directory) are read from the environment.
# Run it only in a network namespace with nothing but loopback.
set -u
cd "$(dirname "$0")/../.."
TAG=${1:?tag}
shift
[ $# -gt 0 ] || set -- target/release/xrce-agent udp4 -p 9000 --dds-interface 127.0.0.1 \
    -v 3 --metrics 127.0.0.1:9100
OUT=${OUT:-target/overload}
mkdir -p "$OUT"
LOADGEN=target/release/xrce-loadgen
"$@" > "$OUT/$TAG-agent.log" 2>&1 &
AGENT=$!
sleep 3
( while kill -0 $AGENT 2>/dev/null; do
    kb=0
    for p in $AGENT $(pgrep -P $AGENT); do
        r=$(awk '/VmRSS/{print $2}' /proc/$p/status 2>/dev/null)
        kb=$((kb + ${r:-0}))
    done
    echo "$(date +%s) $kb"
    sleep 1
  done ) > "$OUT/$TAG-rss.txt" &
$LOADGEN --no-agent --port 9000 --publishers 100 --subscribers 1 --best-effort \
    --rate "${FLOOD_RATE:-0}" --payload 1000 --threads 2 --samples 100000000 --duration 40 \
    --dds-reader false > "$OUT/$TAG-flood.txt" 2>&1 &
FLOOD=$!
sleep "${QUIET_DELAY:-8}"
$LOADGEN --no-agent --port "${QUIET_PORT:-9000}" --domain 1 --first-client-key 0x20000000 \
    --publishers 1 --subscribers 1 --rate 1000 --samples 20000 ${QUIET_ARGS:-} \
    > "$OUT/$TAG-quiet.txt" 2>&1
wait $FLOOD
grep -E "^Udp:" /proc/net/snmp > "$OUT/$TAG-udp.txt"
curl -s 127.0.0.1:9100/metrics \
    | grep -E "^xrce_(dropped|best_effort_sheds|memory_limit_kills|process_resident_memory)" > "$OUT/$TAG-drops.txt"
kill $AGENT
wait $AGENT
echo "== $TAG: quiet pair"
grep -v progress "$OUT/$TAG-quiet.txt" | grep -E "samples in|latency|into DDS" | cut -c1-200
echo "== $TAG: flood"
grep -v progress "$OUT/$TAG-flood.txt" | grep -E "samples in" | cut -c1-120
echo "== $TAG: peak RSS $(sort -k2 -n "$OUT/$TAG-rss.txt" | tail -1 | awk '{printf "%.1f MiB", $2/1024}')"
cat "$OUT/$TAG-drops.txt" "$OUT/$TAG-udp.txt"
