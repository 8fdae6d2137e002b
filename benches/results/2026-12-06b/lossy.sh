#!/bin/bash
# usage: lossy.sh AGENT_CMD(with {port}) LOSS SEEDS N [relay extra args]
# Times the eProsima PublishHelloWorld example (N reliable samples, then DELETE) through the
# impaired relay; prints seconds per run. Runs inside a loopback-only namespace.
agent_cmd=$1; loss=$2; seeds=$3; n=$4; shift 4
port=$((20000 + RANDOM % 20000)); rport=$((port + 1))
${agent_cmd//\{port\}/$port} > /dev/null 2>&1 &
apid=$!
sleep 1.5
for seed in $seeds; do
  coproc RELAY { ${RELAY:-target/release/impaired-relay} --agent 127.0.0.1:$port --listen-port $rport --loss $loss --seed $seed "$@"; }
  sleep 0.2
  t0=$(date +%s.%N)
  timeout 120 ${EXAMPLES:?the eProsima client examples build dir}/PublishHelloWorld/PublishHelloWorldClient 127.0.0.1 $rport $n > /tmp/pub.out 2>&1
  rc=$?
  t1=$(date +%s.%N)
  sent=$(grep -c "Send topic" /tmp/pub.out)
  exec {RELAY[1]}>&-
  counts=$(tail -1 <&${RELAY[0]})
  wait $RELAY_PID 2>/dev/null
  printf "loss %s seed %s: %.1f s (rc %s, %s samples sent) %s\n" $loss $seed $(echo "$t1 - $t0" | bc) $rc $sent "$counts"
done
kill $apid; wait $apid 2>/dev/null
