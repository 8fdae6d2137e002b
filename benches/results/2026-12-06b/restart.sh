#!/bin/bash
# The eProsima HelloWorld publisher and subscriber (30 samples) through a kill of the whole
# agent (the supervisor SIGKILLed) restarted after $1 seconds. Prints what the subscriber got.
delay=$1; agent=${2:-${AGENT_NEW:?this build of xrce-agent}}
port=$((20000 + RANDOM % 20000))
start() { $agent udp4 -p $port --dds-interface 127.0.0.1 -v ${VERB:-4} >> /tmp/restart-agent.log 2>&1 & echo $!; }
: > /tmp/restart-agent.log
apid=$(start); sleep 1.5
E=${EXAMPLES:?the eProsima client examples build dir}
$E/SubscribeHelloWorld/SubscribeHelloWorldClient 127.0.0.1 $port ${N:-30} > /tmp/sub.out 2>&1 &
spid=$!; sleep 1
$E/PublishHelloWorld/PublishHelloWorldClient 127.0.0.1 $port ${N:-30} > /tmp/pub.out 2>&1 &
ppid=$!
sleep ${3:-5.3}
echo "kill at $(date -u +%T.%N)" >> /tmp/restart-agent.log; kill -9 $apid; sleep $delay; apid=$(start)
wait $ppid; sleep 2; kill $spid 2>/dev/null
echo "delay $delay: published $(grep -c 'Send topic' /tmp/pub.out), received $(grep -c 'Received topic' /tmp/sub.out)"
kill $apid; wait $apid 2>/dev/null
