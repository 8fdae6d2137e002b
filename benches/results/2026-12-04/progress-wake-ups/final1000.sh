#!/bin/sh
ip link set lo up
A=/tmp/final/xrce-agent
B=/tmp/head259/xrce-agent
C="udp4 -p {port} --dds-interface 127.0.0.1 -v 2"
/tmp/final/xrce-loadgen --publishers 1000 --subscribers 1 --rate 20000 --payload 40 --best-effort \
  --samples 200000 --rounds 3 --agent-cmd "$A $C" --compare-with "$B $C" > /tmp/lazyab/final-ab-1000clients-20k.txt 2>&1
/tmp/final/xrce-loadgen --publishers 100 --subscribers 1 --rate 20000 --payload 40 \
  --samples 200000 --rounds 3 --agent-cmd "$A $C" --compare-with "$B $C" > /tmp/lazyab/final-ab-100clients-20k-reliable.txt 2>&1
echo done
