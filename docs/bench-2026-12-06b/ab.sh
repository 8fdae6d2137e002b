#!/bin/sh
# Before (e4829dd) and after issue 42's change, alternating round by round, in a
# network namespace with only loopback: unshare -n sh -c 'ip link set lo up; sh ab.sh'
# NEW and OLD are the two release builds of xrce-agent (copied aside), L the generator.
L=${L:-/tmp/ab/loadgen}
NEW=${NEW:-/tmp/ab/new-agent}
OLD=${OLD:-/tmp/ab/old-agent}
export XRCE_DISCARD_SESSIONS=true
A="$NEW udp4 -p {port} --dds-interface 127.0.0.1 -v 2"
B="$OLD udp4 -p {port} --dds-interface 127.0.0.1 -v 2"
$L --publishers 1 --subscribers 1 --rate 10000 --payload 40 --best-effort --samples 100000 --rounds 3 --agent-cmd "$A" --compare-with "$B"
$L --publishers 10 --subscribers 1 --rate 1000 --payload 40 --best-effort --samples 20000 --rounds 3 --agent-cmd "$A" --compare-with "$B"
$L --publishers 100 --subscribers 1 --rate 20000 --payload 40 --best-effort --samples 200000 --rounds 3 --agent-cmd "$A" --compare-with "$B"
