#!/bin/bash
ip link set lo up
L=/tmp/lazy/xrce-loadgen
for r in 1 2; do
for b in lazy head259; do
  /tmp/$b/xrce-agent --config /tmp/cs/gw.toml > /tmp/cs/ctx-$b.log 2>&1 &
  AG=$!
  sleep 3
  $L --no-agent --port 9000 --subscriber-port 9001 --publishers 100 --subscribers 1 --rate 20000 --payload 40 --best-effort --samples 200000 ${EXTRA:-} > /tmp/cs/ctx-$b-lg.txt 2>&1
  for p in $(pgrep -P $AG); do fds=$(ls /proc/$p/fd | wc -l);
    name=$(tr '\0' ' ' < /proc/$p/cmdline | awk '{print $1}' | xargs basename)
    v=0; n=0
    for t in /proc/$p/task/*; do
      a=$(awk '/^voluntary_ctxt_switches/{print $2}' $t/status); v=$((v+a))
      c=$(awk '/^nonvoluntary_ctxt_switches/{print $2}' $t/status); n=$((n+c))
    done
    echo "$r $b $name fds $fds voluntary $v nonvoluntary $n"
  done
  grep -E "samples in|us/sample" /tmp/cs/ctx-$b-lg.txt | grep -v progress | head -2
  kill $AG; wait $AG
done
done
