#!/bin/sh
ip link set lo up
cd /work/main
A=/tmp/lazy/xrce-agent
B=/tmp/head259/xrce-agent
L=/tmp/lazy/xrce-loadgen
O=/tmp/lazyab
mkdir -p $O
C="udp4 -p {port} --dds-interface 127.0.0.1 -v 2"
$L --publishers 100 --subscribers 1 --rate 20000 --payload 40 --best-effort --samples 200000 --rounds 3 \
  --agent-cmd "$A $C" --compare-with "$B $C" > $O/ab-100clients-20k.txt 2>&1
$L --publishers 1 --subscribers 1 --rate 10000 --payload 40 --best-effort --samples 100000 --rounds 3 \
  --agent-cmd "$A $C" --compare-with "$B $C" > $O/ab-latency-10k.txt 2>&1
$L --publishers 1 --subscribers 1 --rate 1000 --payload 40 --best-effort --samples 20000 --rounds 3 \
  --agent-cmd "$A $C" --compare-with "$B $C" > $O/ab-latency-1k.txt 2>&1
$L --publishers 100 --subscribers 1 --rate 60000 --payload 40 --best-effort --samples 600000 --rounds 3 \
  --agent-cmd "$A $C" --compare-with "$B $C" > $O/ab-100clients-60k.txt 2>&1
echo done
