#!/bin/bash
# Voluntary / involuntary context switches per process and per thread, after one 10 s run of
# 100 best-effort publishers at 20,000 samples/s. MODE=gateway: publishers and the subscriber
# on two front-ends of one worker (gateway.toml); MODE=single: one UDP front-end.
ip link set lo up
L=/tmp/final/xrce-loadgen
for r in 1 2; do
for b in final head259; do
  if [ "$MODE" = gateway ]; then
    /tmp/$b/xrce-agent --config /tmp/cs/gw.toml > /tmp/cs/ctx-$b.log 2>&1 &
    SUB="--subscriber-port 9001"
  else
    /tmp/$b/xrce-agent udp4 -p 9000 --dds-interface 127.0.0.1 -v 2 > /tmp/cs/ctx-$b.log 2>&1 &
    SUB=""
  fi
  AG=$!
  sleep 3
  $L --no-agent --port 9000 $SUB --publishers 100 --subscribers 1 --rate 20000 --payload 40 --best-effort --samples 200000 > /tmp/cs/ctx-$b-lg.txt 2>&1
  for p in $(pgrep -P $AG); do
    fds=$(ls /proc/$p/fd | wc -l)
    v=0; n=0; per=""
    for t in /proc/$p/task/*; do
      a=$(awk '/^voluntary_ctxt_switches/{print $2}' $t/status); v=$((v+a))
      c=$(awk '/^nonvoluntary_ctxt_switches/{print $2}' $t/status); n=$((n+c))
      per="$per $(cat $t/comm | tr ' ' _)=$a"
    done
    echo "$r $b fds $fds voluntary $v nonvoluntary $n |$per"
  done
  grep -E "samples in" /tmp/cs/ctx-$b-lg.txt | grep -v progress | head -1
  kill $AG; wait $AG
done
done
