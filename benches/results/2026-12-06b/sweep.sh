#!/bin/bash
# Kill phases across the publisher's one-second cycle, restart 0.5 s later, both builds.
for a in ${AGENT_NEW:?this build of xrce-agent} ${AGENT_OLD:?the previous build of xrce-agent}; do
  for ph in 5.00 5.10 5.20 5.30 5.40 5.50 5.60 5.70 5.80 5.85 5.90 5.95 5.98 6.00 6.02 6.05; do
    N=10 unshare -n bash -c "ip link set lo up; N=10 ./restart.sh 0.5 $a $ph" 2>&1 | tail -1 | sed "s|^|${a##*/} phase $ph: |"
  done
done
