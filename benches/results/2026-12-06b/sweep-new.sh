#!/bin/bash
for ph in 5.00 5.10 5.20 5.30 5.40 5.50 5.60 5.70 5.80 5.85 5.90 5.95 5.98 6.00 6.02 6.05; do
  N=10 unshare -n bash -c "ip link set lo up; N=10 ./restart.sh 0.5 ${AGENT_NEW:?this build of xrce-agent} $ph" 2>&1 | tail -1 | sed "s|^|new-agent phase $ph: |"
done
