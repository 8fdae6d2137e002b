#!/bin/sh
# Where the time of one sample goes at 1,000/s (issue 45): 10 best-effort publishers -> 1 XRCE
# subscriber through the agent, 40-byte samples, the generator's RustDDS reader also reading
# them from DDS. One agent (release build of this tree), three windows of the measured phase:
#   clean    20 s untouched: CPU (user, system) and context switches per sample, per process
#   syscalls 10 s under `strace -c -f` (slows the processes; the counts are what matter)
#   profile  10 s under `perf record -g` (kernel symbols need root outside a user namespace)
# Output under OUT (default benches/results/<today>/breakdown): clean.txt (per sample),
# strace-*.txt, perf-*.txt, loadgen.txt. DDS and every socket stay on loopback: it enters a
# network namespace with only loopback itself (`unshare -n` as root, else `unshare -rn`).
#
#   benches/scripts/breakdown.sh
set -eu
here=$(cd "$(dirname "$0")/../.." && pwd)
if [ "${XRCE_BD_IN_NETNS:-}" != 1 ]; then
  export XRCE_BD_IN_NETNS=1
  for flags in -n -rn; do
    if unshare $flags true 2>/dev/null; then
      exec unshare $flags sh -c 'ip link set lo up && exec sh "$0" "$@"' "$0" "$@"
    fi
  done
  echo "breakdown.sh: cannot enter a network namespace (unshare -n)" >&2
  exit 1
fi
R=${R:-$here/target/release}
OUT=${OUT:-$here/benches/results/$(date +%F)/breakdown}
mkdir -p "$OUT"
XRCE_RUNTIME_DIR=$(mktemp -d)
export XRCE_RUNTIME_DIR
export XRCE_DISCARD_SESSIONS=true
AG=
LG=
# Whatever happens, nothing is left running and the runtime directory goes.
cleanup() {
  for p in $LG $AG; do kill "$p" 2>/dev/null || true; done
  wait 2>/dev/null || true
  rm -rf "$XRCE_RUNTIME_DIR"
}
trap cleanup EXIT
"$R/xrce-agent" udp4 -p 9999 --dds-interface 127.0.0.1 -v 2 >"$OUT/agent.log" 2>&1 &
AG=$!
sleep 4
FE=$(pgrep -P $AG -f " frontend" | head -1)
WK=$(pgrep -P $AG -f " dds-worker" | head -1)
if [ -z "$FE" ] || [ -z "$WK" ]; then
  echo "breakdown.sh: the agent's front-end or worker did not start (see $OUT/agent.log)" >&2
  exit 1
fi
"$R/xrce-loadgen" --no-agent --port 9999 --publishers 10 --subscribers 1 --rate 1000 \
  --best-effort --samples 60000 --payload 40 >"$OUT/loadgen.txt" 2>&1 &
LG=$!
ticks() { # pid -> user and system ticks, voluntary and involuntary context switches
  echo "$(awk '{print $14, $15}' /proc/$1/stat)" \
    "$(awk '/^voluntary_ctxt/ {v=$2} /^nonvoluntary_ctxt/ {n=$2} END {print v, n}' /proc/$1/status)"
}
sleep 12
a_fe=$(ticks $FE); a_wk=$(ticks $WK); a_lg=$(ticks $LG)
sleep 20
b_fe=$(ticks $FE); b_wk=$(ticks $WK); b_lg=$(ticks $LG)
hz=$(getconf CLK_TCK)
{
  echo "per sample over 20 s at 1,000/s (20,000 samples): CPU µs (user + system), context switches"
  for p in "front-end:$a_fe:$b_fe" "worker:$a_wk:$b_wk" "generator:$a_lg:$b_lg"; do
    echo "$p" | awk -F: -v hz="$hz" '{
      split($2, a, " "); split($3, b, " "); n = 20000; t = 1e6 / hz / n
      printf "%-10s %5.1f µs (%4.1f user + %4.1f system), %4.2f voluntary + %4.2f involuntary switches\n",
        $1, (b[1]-a[1]+b[2]-a[2])*t, (b[1]-a[1])*t, (b[2]-a[2])*t, (b[3]-a[3])/n, (b[4]-a[4])/n }'
  done
} >"$OUT/clean.txt"
timeout -s INT 10 strace -c -f -p $FE -o "$OUT/strace-frontend.txt" >/dev/null 2>&1 &
S1=$!
timeout -s INT 10 strace -c -f -p $WK -o "$OUT/strace-worker.txt" >/dev/null 2>&1 &
S2=$!
wait $S1 || true
wait $S2 || true
sleep 1
perf record -F 4999 -g -p $FE -o "$OUT/perf-frontend.data" -- sleep 10 >/dev/null 2>&1 &
P1=$!
perf record -F 4999 -g -p $WK -o "$OUT/perf-worker.data" -- sleep 10 >/dev/null 2>&1 &
P2=$!
wait $P1 || true
wait $P2 || true
wait $LG || true
LG=
kill $AG
wait $AG || true
AG=
for p in frontend worker; do
  {
    perf report -i "$OUT/perf-$p.data" --no-children --sort dso --stdio -g none 2>/dev/null | grep -v '^#' | grep -v '^$' | head -6
    echo
    perf report -i "$OUT/perf-$p.data" --no-children --sort sym --stdio -g none 2>/dev/null | grep -v '^#' | grep -v '^$' | head -40
  } >"$OUT/perf-$p.txt"
  rm -f "$OUT/perf-$p.data"
done
cat "$OUT/clean.txt"
