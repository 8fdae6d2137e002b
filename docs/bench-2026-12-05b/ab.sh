#!/bin/sh
# The usual benchmarks: this session's build (A, /tmp/new) against the build before it
# (B, /tmp/base = 563d230, the twenty-second session's last commit), alternated by
# xrce-loadgen, 3 rounds each, medians.
# Run as: unshare -n sh docs/bench-2026-12-05b/ab.sh OUT_DIR
set -e
ip link set lo up
# Each round starts a fresh agent on the same port: without this it would take over the
# sessions the previous round stored (what a restarted agent does), which no benchmark wants.
export XRCE_DISCARD_SESSIONS=true
O=${1:-/tmp/ab}
mkdir -p "$O"
A=/tmp/new/xrce-agent
B=/tmp/base/xrce-agent
L=/tmp/new/xrce-loadgen
C="udp4 -p {port} --dds-interface 127.0.0.1 -v 2"
$L --publishers 1000 --subscribers 1 --rate 20000 --payload 40 --best-effort --samples 200000 --rounds 3 \
  --agent-cmd "$A $C" --compare-with "$B $C" > "$O/ab-1000clients-20k.txt" 2>&1
$L --publishers 1 --subscribers 1 --rate 10000 --payload 40 --best-effort --samples 100000 --rounds 3 \
  --agent-cmd "$A $C" --compare-with "$B $C" > "$O/ab-latency-10k.txt" 2>&1
$L --publishers 1 --subscribers 1 --rate 1000 --payload 40 --best-effort --samples 20000 --rounds 3 \
  --agent-cmd "$A $C" --compare-with "$B $C" > "$O/ab-latency-1k.txt" 2>&1
$L --publishers 100 --subscribers 1 --rate 20000 --payload 40 --samples 200000 --rounds 3 \
  --agent-cmd "$A $C" --compare-with "$B $C" > "$O/ab-100clients-20k-reliable.txt" 2>&1
echo done
