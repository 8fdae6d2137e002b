#!/bin/sh
# The current build (A, /tmp/new) against eProsima's MicroXRCEAgent v2.4.2 (B), built from
# source outside the repository against Debian's Fast DDS 2.9.1 (cmake -DUAGENT_SUPERBUILD=OFF
# -DUAGENT_USE_SYSTEM_FASTDDS=ON -DUAGENT_USE_SYSTEM_FASTCDR=ON -DUAGENT_P2P_PROFILE=OFF
# -DUAGENT_LOGGER_PROFILE=OFF -DUAGENT_SOCKETCAN_PROFILE=OFF, in /tmp/ref-build), alternated
# by xrce-loadgen, 3 rounds each, medians. Best-effort, 40-byte samples.
# Run as: unshare -n sh benches/results/2026-12-05b/ref.sh OUT_DIR
set -e
ip link set lo up
export XRCE_DISCARD_SESSIONS=true
O=${1:-/tmp/ref}
mkdir -p "$O"
L=/tmp/new/xrce-loadgen
A="/tmp/new/xrce-agent udp4 -p {port} --dds-interface 127.0.0.1 -v 2"
B="/tmp/ref-build/MicroXRCEAgent udp4 -p {port} -v 0"
$L --publishers 1 --subscribers 1 --rate 1000 --payload 40 --best-effort --samples 10000 --rounds 3 \
  --agent-cmd "$A" --compare-with "$B" > "$O/ref-latency-1k.txt" 2>&1
$L --publishers 1 --subscribers 1 --rate 10000 --payload 40 --best-effort --samples 100000 --rounds 3 \
  --agent-cmd "$A" --compare-with "$B" > "$O/ref-latency-10k.txt" 2>&1
$L --publishers 100 --subscribers 1 --rate 20000 --payload 40 --best-effort --samples 200000 --rounds 3 \
  --agent-cmd "$A" --compare-with "$B" > "$O/ref-100clients-20k.txt" 2>&1
$L --publishers 100 --subscribers 1 --rate 60000 --payload 40 --best-effort --samples 600000 --rounds 3 \
  --agent-cmd "$A" --compare-with "$B" > "$O/ref-100clients-60k.txt" 2>&1
echo done
