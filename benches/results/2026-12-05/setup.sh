#!/bin/sh
# Set-up of 1,001 sessions and 4,004 entities, the two builds of ab.sh alternated, 7 rounds
# (the 3 rounds of ab.sh left the set-up medians apart: 679 against 591 ms).
# Run as: unshare -n sh benches/results/2026-12-05/setup.sh OUT_DIR
set -e
ip link set lo up
export XRCE_DISCARD_SESSIONS=true
O=${1:-/tmp/ab}
C="udp4 -p {port} --dds-interface 127.0.0.1 -v 2"
/tmp/new/xrce-loadgen --publishers 1000 --subscribers 1 --rate 20000 --payload 40 --best-effort \
  --samples 20000 --rounds 7 --agent-cmd "/tmp/new/xrce-agent $C" \
  --compare-with "/tmp/base/xrce-agent $C" > "$O/ab-1000clients-setup${RUN:-}.txt" 2>&1
echo done
