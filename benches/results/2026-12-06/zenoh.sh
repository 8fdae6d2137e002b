#!/bin/sh
# Issue 35: the agent into Zenoh (-m zenoh) beside Cyclone DDS (its default), one run, in a
# network namespace with only loopback (run as root from the repository's top folder):
#   unshare -n sh -c 'ip link set lo up; benches/results/2026-12-06/zenoh.sh'
# Cyclone rows: the generator's RustDDS reader counts what reaches DDS. Zenoh rows: the
# generator runs a Zenoh router on tcp/127.0.0.1:17447 (the agent connects to it, as an
# rmw_zenoh node to its router) and counts what reaches its subscription there.
# (`--rounds 3` below is ignored: only `--compare-with` runs rounds; each row is one run.)
set -e
L=target/release/xrce-loadgen
A="target/release/xrce-agent udp4 -p {port} --dds-interface 127.0.0.1 -v 2"
Z="target/release/xrce-agent udp4 -p {port} -m zenoh -v 2"
export XRCE_DISCARD_SESSIONS=true
for rate in 1000 10000; do
  n=$((rate * 10))
  echo "=== 1 -> 1, $rate/s: Cyclone DDS"
  $L --publishers 1 --subscribers 1 --rate $rate --payload 40 --best-effort --samples $n --rounds 3 --agent-cmd "$A"
  echo "=== 1 -> 1, $rate/s: Zenoh"
  $L --publishers 1 --subscribers 1 --rate $rate --payload 40 --best-effort --samples $n --rounds 3 --agent-cmd "$Z" --zenoh-router tcp/127.0.0.1:17447
done
echo "=== 100 -> 1, 20000/s: Cyclone DDS"
$L --publishers 100 --subscribers 1 --rate 20000 --payload 40 --best-effort --samples 200000 --rounds 3 --agent-cmd "$A"
echo "=== 100 -> 1, 20000/s: Zenoh"
$L --publishers 100 --subscribers 1 --rate 20000 --payload 40 --best-effort --samples 200000 --rounds 3 --agent-cmd "$Z" --zenoh-router tcp/127.0.0.1:17447
