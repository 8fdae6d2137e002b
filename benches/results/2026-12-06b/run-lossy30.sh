#!/bin/bash
for agent in "${AGENT_NEW:?this build of xrce-agent} udp4 -p {port} --dds-interface 127.0.0.1 -v 0" "${AGENT_REF:?MicroXRCEAgent} udp4 -p {port} -v 0"; do
  echo "== ${agent%% *}"
  unshare -n bash -c "ip link set lo up; ./lossy.sh '$agent' 0.3 '5 6 7 8 9 10 11 12' 20"
done
