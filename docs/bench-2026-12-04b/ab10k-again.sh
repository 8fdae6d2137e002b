#!/bin/sh
ip link set lo up
export XRCE_DISCARD_SESSIONS=true
A=/tmp/new/xrce-agent
B=/tmp/base/xrce-agent
L=/tmp/new/xrce-loadgen
C="udp4 -p {port} --dds-interface 127.0.0.1 -v 2"
$L --publishers 1 --subscribers 1 --rate 10000 --payload 40 --best-effort --samples 100000 --rounds 3 \
  --agent-cmd "$A $C" --compare-with "$B $C" > /tmp/ab/ab-latency-10k-again.txt 2>&1
