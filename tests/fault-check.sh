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
  # The same agent code in one process, in memory (simulation.rs installs XRCE_FAULT itself).
  "dds-duplicate    simulation::samples_reach_the_clients_reader_through_the_worker_in_order"
  "dds-drop         simulation::samples_reach_the_clients_reader_through_the_worker_in_order"
  "client-duplicate simulation::samples_reach_the_clients_reader_through_the_worker_in_order"
  "client-drop      simulation::a_lossy_link_and_a_worker_crash_delay_samples_but_lose_and_repeat_none"
  "replay-skip      simulation::a_lossy_link_and_a_worker_crash_delay_samples_but_lose_and_repeat_none"
  "executed-ignored simulation::a_frontend_that_dies_between_handing_over_and_storing_repeats_no_write"
  "origin-ignored   simulation::a_worker_that_dies_between_delivering_a_sample_and_acknowledging_its_write_repeats_none"
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
if ! tests/e2e-binaries >"$logs/binaries" 2>"$logs/build"; then
  tail -n 30 "$logs/build"
  echo "fault-check: building the tests failed" >&2
  exit 1
fi
exe=$(awk '$1 == "e2e" { print $2 }' "$logs/binaries")
if [ -z "$exe" ]; then
  echo "fault-check: no end-to-end test binary found" >&2
  exit 1
fi

# Runs the named tests side by side in one process (each module keeps to DDS domains of its
# own, so tests of different modules do not see each other), under XRCE_FAULT=$1 (none: no
# fault), into the log $2; libtest writes each test's result on a line of its own into
# $2.results (the log itself may have a child's output in the middle of a result line).
run() {
  local fault=$1 log=$2
  shift 2
  if [ "$fault" = none ]; then
    (cd tests && env -u XRCE_FAULT "$exe" --exact --logfile "$log.results" "$@") >"$log" 2>&1
  else
    (cd tests && XRCE_FAULT=$fault "$exe" --exact --logfile "$log.results" "$@") >"$log" 2>&1
  fi
  return 0
}

# What the run of the log $1 says of the test $2: ok, FAILED, or nothing when it did not run.
outcome() {
  awk -v t="$2" '$2 == t && $1 == "ok" { print "ok"; exit }
                 $2 == t && $1 == "failed" { print "FAILED"; exit }' "$1.results" 2>/dev/null
}

# The captured output of the failed test $2 in the log $1 (libtest prints it after the run).
section() {
  awk -v head="---- $2 stdout ----" '
    $0 == head { on = 1; next }
    on && (/^---- .* stdout ----$/ || /^failures:$/) { exit }
    on { print }' "$1"
}

# The first assertion message of a failed test, on one line.
why() {
  grep -m1 -A1 "panicked at" <<<"$1" | tail -n 1 | cut -c1-110
}

declare -A control=()
declare -A wanted=()
faults=()
for c in "${checks[@]}"; do
  read -r fault test <<<"$c"
  [ -n "$only" ] && [ "$fault" != "$only" ] && continue
  control[$test]=unknown
  if [ -z "${wanted[$fault]:-}" ]; then
    faults+=("$fault")
  fi
  wanted[$fault]+=" $test"
done

missed=0
report=()
# Every test without a fault first: each must pass.
start=$SECONDS
run none "$logs/none" "${!control[@]}"
for test in "${!control[@]}"; do
  result=$(outcome "$logs/none" "$test")
  if [ "$result" = ok ]; then
    control[$test]=green
    echo "without a fault  $test: passed"
  elif [ "$result" != FAILED ]; then
    control[$test]=red
    missed=$((missed + 1))
    echo "without a fault  $test: did not run:"
    tail -n 5 "$logs/none"
    report+=("$(printf '%-17s %-95s %s' none "$test" "DID NOT RUN")")
  else
    control[$test]=red
    missed=$((missed + 1))
    echo "without a fault  $test: FAILED: $(why "$(section "$logs/none" "$test")")"
    report+=("$(printf '%-17s %-95s %s' none "$test" "FAILED without a fault")")
  fi
done
echo "(without a fault: $((SECONDS - start)) s)"
# Then each fault against the tests that must catch it: each must fail on an assertion, with
# an agent that said the fault was active.
for fault in "${faults[@]}"; do
  read -r -a tests <<<"${wanted[$fault]}"
  log="$logs/$fault"
  start=$SECONDS
  run "$fault" "$log" "${tests[@]}"
  for test in "${tests[@]}"; do
    result=$(outcome "$log" "$test")
    out=$(section "$log" "$test")
    if [ "$result" = ok ]; then
      missed=$((missed + 1))
      echo "XRCE_FAULT=$fault  $test: passed: NOT CAUGHT"
      report+=("$(printf '%-17s %-95s %s' "$fault" "$test" "NOT CAUGHT")")
    elif [ "$result" != FAILED ]; then
      missed=$((missed + 1))
      echo "XRCE_FAULT=$fault  $test: did not run:"
      tail -n 5 "$log"
      report+=("$(printf '%-17s %-95s %s' "$fault" "$test" "DID NOT RUN")")
    elif ! grep -q "FAULT INJECTION active" <<<"$out"; then
      # Red without the fault running (the agent did not start, a name it does not know, a
      # harness failure) proves nothing.
      missed=$((missed + 1))
      echo "XRCE_FAULT=$fault  $test: failed, but no agent reported the fault active:"
      grep -m1 -A1 "panicked at" <<<"$out" || tail -n 5 <<<"$out"
      report+=("$(printf '%-17s %-95s %s' "$fault" "$test" "FAILED WITHOUT THE FAULT ACTIVE")")
    elif grep -q "panicked at" <<<"$out"; then
      echo "XRCE_FAULT=$fault  $test: caught: $(why "$out")"
      report+=("$(printf '%-17s %-95s %s' "$fault" "$test" "caught: $(why "$out")")")
    else
      # Red without an assertion (a harness failure) proves nothing.
      missed=$((missed + 1))
      echo "XRCE_FAULT=$fault  $test: failed without an assertion:"
      tail -n 5 <<<"$out"
      report+=("$(printf '%-17s %-95s %s' "$fault" "$test" "FAILED WITHOUT AN ASSERTION")")
    fi
  done
  echo "(XRCE_FAULT=$fault: $((SECONDS - start)) s)"
done

echo
echo "=== fault check: what caught what ==="
[ "${#report[@]}" -gt 0 ] && printf '%s\n' "${report[@]}"
if [ "$missed" -gt 0 ]; then
  echo "fault check: $missed check(s) failed"
  exit 1
fi
echo "fault check: every fault caught, every test green without it"
