#!/bin/sh
ip link set lo up
A=/tmp/lazy/xrce-agent
B=/tmp/head259/xrce-agent
L=/tmp/lazy/xrce-loadgen
O=/tmp/lazyab
$L --port 9000 --subscriber-port 9001 --publishers 100 --subscribers 1 --rate 20000 --payload 40 --best-effort --samples 200000 --rounds 3 \
  --agent-cmd "$A --config /tmp/cs/gw.toml" --compare-with "$B --config /tmp/cs/gw.toml" > $O/ab-100clients-20k-publishers-own-frontend.txt 2>&1
echo done
