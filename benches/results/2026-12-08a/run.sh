#!/bin/sh
# How kill-soak-*.txt were made (AGENT: a release build of the commit named in
# BENCHMARKS.md): 100 reliable publishers and 1 subscriber at 1,000 samples/s in all,
# 100,000 samples, the worker (or the worker and the front-end in turn) SIGKILLed every
# 6 s, 14 kills (a run named worker-old-1 kills the worker: what follows the first dash
# only names the output); in a namespace with only loopback:
#   unshare -rn sh -c "ip link set lo up; sh run.sh worker-1 alternate-1"
cd "$(dirname "$0")/../../.."
export XRCE_RUNTIME_DIR=$(mktemp -d) XRCE_DISCARD_SESSIONS=true
O=benches/results/2026-12-08a
AGENT="${AGENT:-target/release/xrce-agent} udp4 -p 8888 --dds-interface 127.0.0.1 -v 2"
for run in "$@"; do
  kill=${run%%-*}
  ./target/release/xrce-loadgen --publishers 100 --subscribers 1 --rate 1000 \
    --samples 100000 --duration 110 --kills 14 --kill "$kill" --kill-every 6 \
    --agent-cmd "$AGENT" > $O/kill-soak-$run.txt 2>&1
done
