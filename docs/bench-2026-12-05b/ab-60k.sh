#!/bin/sh
# 100 best-effort publishers at 60,000/s offered, this session's build (A, /tmp/new) against
# 563d230 (B, /tmp/base): whether what ref.sh measured for ours at 60,000/s (a sixth lost) is
# this VM's or a change's. Run as: unshare -n sh docs/bench-2026-12-05b/ab-60k.sh OUT_DIR
set -e
ip link set lo up
export XRCE_DISCARD_SESSIONS=true
O=${1:-/tmp/ab}
C="udp4 -p {port} --dds-interface 127.0.0.1 -v 2"
/tmp/new/xrce-loadgen --publishers 100 --subscribers 1 --rate 60000 --payload 40 --best-effort \
  --samples 600000 --rounds 3 --agent-cmd "/tmp/new/xrce-agent $C" \
  --compare-with "/tmp/base/xrce-agent $C" > "$O/ab-100clients-60k.txt" 2>&1
echo done
