#!/usr/bin/env python3
"""Time from a client's reset to its first sample in DDS again, for any agent.

usage: recovery.py --agent-cmd "CMD ... {port}" --pattern uros|px4 [--n 15] [--rounds 4]
Runs the agent, a Cyclone DDS reader of rt/chatter (std_msgs/String), and lifecycle_client
(the eProsima client library) that resets between rounds without DELETE. Prints per round:
session re-established after, first sample in DDS after, and the totals.
"""
import argparse, json, os, shlex, signal, socket, subprocess, sys, threading, time

ap = argparse.ArgumentParser()
ap.add_argument("--agent-cmd", required=True)
ap.add_argument("--pattern", default="uros")
ap.add_argument("--n", type=int, default=15)
ap.add_argument("--rounds", type=int, default=4)
ap.add_argument("--client", default=os.environ.get("LIFECYCLE_CLIENT", "lifecycle_client"))
ap.add_argument("--repo", default=os.environ.get("XRCE_REPO", "."))
ap.add_argument("--best-effort-reader", action="store_true")
a = ap.parse_args()

s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM); s.bind(("127.0.0.1", 0)); port = s.getsockname()[1]; s.close()
agent = subprocess.Popen(shlex.split(a.agent_cmd.format(port=port)), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
time.sleep(1.5)
env = dict(os.environ, CYCLONEDDS_URI=os.environ.get("READER_URI") or "file://" + os.path.join(os.path.abspath(a.repo), "tests/python/cyclonedds-loopback.xml"))
py = os.path.join(a.repo, "target/cyclonedds-venv/bin/python")
reader = subprocess.Popen([py, os.path.join(a.repo, "tests/python/dds_peer.py"), "read", "--ros-string", "--topic", "rt/chatter", "--count", "100000", "--timeout", "120"] + (["--best-effort"] if a.best_effort_reader else []), stdout=subprocess.PIPE, env=env, text=True)
arrivals = {}
dupes = [0]
def pump():
    for line in reader.stdout:
        t = time.monotonic()
        if line.startswith("{"):
            i = json.loads(line)["index"]
            if i in arrivals: dupes[0] += 1
            else: arrivals[i] = t
threading.Thread(target=pump, daemon=True).start()
time.sleep(2.0)
out = subprocess.run([a.client, "127.0.0.1", str(port), a.pattern, str(a.n), str(a.rounds)], capture_output=True, text=True, timeout=300).stdout
time.sleep(3.0)
rounds, sessions, created = {}, {}, {}
for l in out.splitlines():
    f = l.split()
    if f and f[0] == "ROUND": rounds[int(f[1])] = float(f[2])
    if f and f[0] == "SESSION": sessions[int(f[1])] = float(f[2])
    if f and f[0] == "CREATED": created[int(f[1])] = (float(f[2]), f[4:])
for r in range(1, a.rounds):
    first = arrivals.get(r * a.n)
    got = sum(1 for i in range(r * a.n, (r + 1) * a.n) if i in arrivals)
    print(f"round {r}: session {1000*(sessions.get(r, float('nan'))-rounds[r]):.0f} ms, objects {1000*(created[r][0]-rounds[r]):.0f} ms statuses {' '.join(created[r][1])}, "
          f"first sample in DDS {('%.0f ms' % (1000*(first-rounds[r]))) if first else 'never'}, {got}/{a.n} of the round")
total = a.n * a.rounds
print(f"delivered {sum(1 for i in range(total) if i in arrivals)}/{total}, repeated {dupes[0]}")
reader.kill(); os.killpg(agent.pid, signal.SIGTERM); agent.wait(timeout=20)
