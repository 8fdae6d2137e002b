#!/bin/sh
# Kill soak of each build (A = /tmp/new, this session; B = /tmp/base = 563d230): 100 reliable
# publishers, 1 reliable subscriber, 1,000/s, the worker and the front-end SIGKILLed in turn
# every 6 s, 14 kills. Run as: unshare -n sh benches/results/2026-12-05b/kill-soak.sh OUT_DIR
set -e
ip link set lo up
export XRCE_DISCARD_SESSIONS=true
O=${1:-/tmp/ab}
C="udp4 -p {port} --dds-interface 127.0.0.1 -v 2"
for b in new base; do
  /tmp/new/xrce-loadgen --publishers 100 --subscribers 1 --rate 1000 --samples 100000 \
    --duration 110 --kills 14 --kill alternate --kill-every 6 \
    --agent-cmd "/tmp/$b/xrce-agent $C" > "$O/kill-soak-14-$b.txt" 2>&1
done
echo done
