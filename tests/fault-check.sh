#!/usr/bin/env bash
# Proves that the end-to-end tests catch the defects a user would see: runs each fault the
# agent can inject on purpose (XRCE_FAULT; the test harness builds the agent with the cargo
# feature `fault-injection`, which release builds never enable) against the tests that must
# catch it, and prints what caught what. Each test must pass without a fault and fail with
# its fault; the script fails otherwise.
#
#   tests/fault-check.sh            every fault
#   tests/fault-check.sh dds-drop   one
set -uo pipefail
cd "$(dirname "$0")/.."

# fault  module::test-name in the end-to-end binary (the tests that must go red under it)
checks=(
  "dds-duplicate    helloworld_e2e::client_publishes_cyclone_reads_every_sample"
  "dds-duplicate    helloworld_e2e::client_to_client_through_the_agent"
  "dds-drop         helloworld_e2e::client_publishes_cyclone_reads_every_sample"
  "dds-drop         helloworld_e2e::client_to_client_through_the_agent"
  "client-duplicate helloworld_e2e::cyclone_publishes_client_reads"
  "client-duplicate helloworld_e2e::client_to_client_through_the_agent"
  "client-drop      helloworld_e2e::cyclone_publishes_client_reads"
  "client-drop      request_reply::replies_reach_the_requester_matched_to_their_requests"
  "reply-duplicate  request_reply::replies_reach_the_requester_matched_to_their_requests"
  "heartbeat-fixed  heartbeats::heartbeats_to_a_silent_client_back_off"
  "replay-skip      worker_restart::worker_sigkill_while_a_client_reads_resumes_its_samples_none_twice"
)

only=${1:-}
known=$(printf '%s\n' "${checks[@]}" | awk '{print $1}' | sort -u)
if [ -n "$only" ] && ! awk -v f="$only" '$0 == f { found = 1 } END { exit !found }' <<<"$known"; then
  echo "fault-check: no fault named '$only' (known: $(tr '\n' ' ' <<<"$known"))" >&2
  exit 2
fi
logs=$(mktemp -d)
trap 'rm -rf "$logs"' EXIT

# The tests and the agent (with fault injection) as `cargo test --workspace` (README's test
# command) builds them: after it, nothing is built again (tests/e2e-binaries).
declare -A exe=()
if ! tests/e2e-binaries >"$logs/binaries" 2>"$logs/build"; then
  tail -n 30 "$logs/build"
  echo "fault-check: building the tests failed" >&2
  exit 1
fi
while read -r name path; do exe[$name]=$path; done <"$logs/binaries"
if [ "${#exe[@]}" -eq 0 ]; then
  echo "fault-check: no end-to-end test binaries found" >&2
  exit 1
fi

run() { # fault binary name log -> exit status of the test
  local fault=$1 bin=$2 name=$3 log=$4
  if [ -z "${exe[$bin]:-}" ]; then
    echo "fault-check: no test binary $bin" >"$log"
    return 1
  fi
  if [ "$fault" = none ]; then
    (cd tests && env -u XRCE_FAULT "${exe[$bin]}" --exact "$name") >"$log" 2>&1
  else
    (cd tests && XRCE_FAULT=$fault "${exe[$bin]}" --exact "$name") >"$log" 2>&1
  fi
}

# The first assertion message of a failed test, on one line.
why() {
  grep -m1 -A1 "panicked at" "$1" | tail -n 1 | cut -c1-110
}

declare -A control=()
missed=0
report=()
for c in "${checks[@]}"; do
  read -r fault test <<<"$c"
  [ -n "$only" ] && [ "$fault" != "$only" ] && continue
  bin=e2e
  name=$test
  if [ -z "${control[$test]:-}" ]; then
    log="$logs/none.$name"
    start=$SECONDS
    if run none "$bin" "$name" "$log"; then
      control[$test]=green
      echo "without a fault  $test: passed ($((SECONDS - start)) s)"
    else
      control[$test]=red
      missed=$((missed + 1))
      echo "without a fault  $test: FAILED: $(why "$log")"
      report+=("$(printf '%-17s %-95s %s' none "$test" "FAILED without a fault")")
    fi
  fi
  log="$logs/$fault.$name"
  start=$SECONDS
  if run "$fault" "$bin" "$name" "$log"; then
    missed=$((missed + 1))
    echo "XRCE_FAULT=$fault  $test: passed: NOT CAUGHT ($((SECONDS - start)) s)"
    report+=("$(printf '%-17s %-95s %s' "$fault" "$test" "NOT CAUGHT")")
  elif ! grep -q "FAULT INJECTION active" "$log"; then
    # Red without the fault running (the agent did not start, a name it does not know, a
    # harness failure) proves nothing.
    missed=$((missed + 1))
    echo "XRCE_FAULT=$fault  $test: failed, but no agent reported the fault active:"
    grep -m1 -A1 "panicked at" "$log" || tail -n 5 "$log"
    report+=("$(printf '%-17s %-95s %s' "$fault" "$test" "FAILED WITHOUT THE FAULT ACTIVE")")
  elif grep -q "panicked at" "$log"; then
    echo "XRCE_FAULT=$fault  $test: caught ($((SECONDS - start)) s): $(why "$log")"
    report+=("$(printf '%-17s %-95s %s' "$fault" "$test" "caught: $(why "$log")")")
  else
    # Red without an assertion (a build or harness failure) proves nothing.
    missed=$((missed + 1))
    echo "XRCE_FAULT=$fault  $test: failed without an assertion:"
    tail -n 5 "$log"
    report+=("$(printf '%-17s %-95s %s' "$fault" "$test" "FAILED WITHOUT AN ASSERTION")")
  fi
done

echo
echo "=== fault check: what caught what ==="
[ "${#report[@]}" -gt 0 ] && printf '%s\n' "${report[@]}"
if [ "$missed" -gt 0 ]; then
  echo "fault check: $missed check(s) failed"
  exit 1
fi
echo "fault check: every fault caught, every test green without it"
