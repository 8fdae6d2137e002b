#!/bin/bash
for agent in "${AGENT_NEW:?this build of xrce-agent} udp4 -p {port} --dds-interface 127.0.0.1 -v 0" "${AGENT_REF:?MicroXRCEAgent} udp4 -p {port} -v 0" "${AGENT_OLD:?the previous build of xrce-agent} udp4 -p {port} --dds-interface 127.0.0.1 -v 0"; do
  echo "== ${agent%% *}"
  for loss in 0.1 0.3; do
    unshare -n bash -c "ip link set lo up; ./lossy.sh '$agent' $loss '1 2 3 4' 20"
  done
  unshare -n bash -c "ip link set lo up; ./lossy.sh '$agent' 0 '1 2' 10 --drop-first-delete-status" | sed 's/^/delete-status-dropped: /'
done
