#!/bin/sh
# How processes-*.txt were made (AGENT: a release build of 88e2e9e): --processes 2 (A)
# against one process (B), 100 clients from 100 source addresses, 3 rounds; in a namespace
# with only loopback: unshare -rn sh -c "ip link set lo up; sh run.sh unlimited be-20k"
cd "$(dirname "$0")/../../.."
export XRCE_RUNTIME_DIR=$(mktemp -d) XRCE_DISCARD_SESSIONS=true
O=benches/results/2026-12-07m
A="${AGENT:-target/release/xrce-agent} udp4 -p {port} --dds-interface 127.0.0.1 -v 2 --processes 2"
B="${AGENT:-target/release/xrce-agent} udp4 -p {port} --dds-interface 127.0.0.1 -v 2"
for case in "$@"; do
  case $case in
    unlimited) set -- --publishers 100 --subscribers 1 --samples 400000 --duration 30 ;;
    be-20k) set -- --publishers 100 --subscribers 1 --rate 20000 --best-effort --samples 200000 ;;
    be-60k) set -- --publishers 100 --subscribers 1 --rate 60000 --best-effort --samples 600000 ;;
  esac
  echo "== processes 2 (new) vs 1 (old): $case $*" > $O/processes-$case.txt
  ./target/release/xrce-loadgen "$@" --source-addresses 100 --payload 40 --rounds 3 --agent-cmd "$A" --compare-with "$B" >> $O/processes-$case.txt 2>&1
done
