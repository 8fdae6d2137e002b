#!/usr/bin/env python3
"""An independent Zenoh peer for the end-to-end tests (eclipse-zenoh from PyPI, pinned).

It plays what the tests need of a ROS 2 graph on rmw_zenoh, written from rmw_zenoh's
conventions, not from the agent's code: a router, a subscription and a publisher on a data
key (payload: CDR encapsulation header and body; attachment: sequence number, source
timestamp, GID, serialized with zenoh-ext's own serializer), a watcher of the graph's
liveliness tokens, a service client (a query with the attachment) and a transient-local
subscription (zenoh-ext's advanced subscriber with history, as rmw_zenoh makes one).

Every subcommand prints one line per event on stdout, flushed:
  READY                          the entity exists
  SAMPLE {"key", "payload", "attachment"}   a sample (hex)
  TOKEN PUT|DELETE <key>         a liveliness token came or went
  REPLY {"key", "payload", "attachment"}    a reply to a query
  REQUEST <seq> <a> <b> <gid>    a request served
  SENT <i>                       a sample was put
Exit codes: 0 done, 2 usage, 3 timeout.
"""

import argparse
import json
import struct
import sys
import threading
import time

import zenoh
import zenoh.ext as zext


def out(line):
    print(line, flush=True)


def session(args, mode="client"):
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    if args.connect:
        conf.insert_json5("connect/endpoints", json.dumps([args.connect]))
    if getattr(args, "listen", None):
        conf.insert_json5("listen/endpoints", json.dumps(args.listen))
    else:
        conf.insert_json5("listen/endpoints", "[]")
    return zenoh.open(conf)


def attachment(seq, gid):
    """rmw_zenoh's attachment, by zenoh-ext's serializer: (i64 seq, i64 ns, [u8; 16])."""
    return zext.z_serialize((zext.Int64(seq), zext.Int64(time.time_ns()), bytes(gid)))


def attachment_fields(att):
    """(seq, timestamp, gid) of an attachment, by zenoh-ext's deserializer."""
    return zext.z_deserialize(tuple[zext.Int64, zext.Int64, bytes], att)


def cdr_string(text):
    """A std_msgs/String sample as rmw_zenoh sends it: CDR_LE header, length, text, NUL."""
    data = text.encode() + b"\0"
    return b"\x00\x01\x00\x00" + struct.pack("<I", len(data)) + data


def sample_json(s):
    att = s.attachment
    return json.dumps(
        {
            "key": str(s.key_expr),
            "payload": s.payload.to_bytes().hex(),
            "attachment": att.to_bytes().hex() if att is not None else None,
        }
    )


def wait(deadline, done):
    while time.monotonic() < deadline:
        if done.wait(0.05):
            return True
    return False


def cmd_router(args):
    _s = session(args, mode="router")
    out("READY")
    # Until the test closes stdin (or kills it).
    sys.stdin.read()
    return 0


def cmd_sub(args):
    s = session(args)
    got = [0]
    done = threading.Event()

    def on_sample(sample):
        out("SAMPLE " + sample_json(sample))
        got[0] += 1
        if got[0] >= args.count:
            done.set()

    if args.transient_local:
        # As rmw_zenoh makes a reliable transient-local subscription: history from the
        # publishers' caches (late publishers too), and recovery of missed samples.
        _sub = zext.declare_advanced_subscriber(
            s,
            args.key,
            on_sample,
            history=zext.HistoryConfig(detect_late_publishers=True, max_samples=args.count),
            recovery=zext.RecoveryConfig(heartbeat=True),
            subscriber_detection=True,
        )
    else:
        _sub = s.declare_subscriber(args.key, on_sample)
    out("READY")
    if not wait(time.monotonic() + args.timeout, done):
        print(f"TIMEOUT got={got[0]}", file=sys.stderr)
        return 3
    return 0


def cmd_pub(args):
    s = session(args)
    pub = s.declare_publisher(args.key)
    out("READY")
    gid = bytes(range(0xA0, 0xB0))
    time.sleep(args.delay_ms / 1000)
    for i in range(1, args.count + 1):
        pub.put(cdr_string(f"{args.message} {i}"), attachment=attachment(i, gid))
        out(f"SENT {i}")
        time.sleep(args.interval_ms / 1000)
    time.sleep(0.5)
    return 0


def cmd_tokens(args):
    s = session(args)
    seen = set()
    done = threading.Event()

    def on_token(sample):
        kind = "PUT" if sample.kind == zenoh.SampleKind.PUT else "DELETE"
        key = str(sample.key_expr)
        out(f"TOKEN {kind} {key}")
        if kind == "PUT":
            seen.add(key)

    _sub = s.liveliness().declare_subscriber(args.key, on_token, history=True)
    out("READY")
    wait(time.monotonic() + args.timeout, done)
    return 0


def cmd_call(args):
    """A service client: one query per request, as rmw_zenoh's client sends it."""
    s = session(args)
    querier = s.declare_querier(
        args.key,
        target=zenoh.QueryTarget.ALL_COMPLETE,
        consolidation=zenoh.ConsolidationMode.NONE,
        timeout=args.timeout,
    )
    out("READY")
    time.sleep(args.delay_ms / 1000)
    gid = bytes(range(0xC0, 0xD0))
    for i in range(1, args.count + 1):
        payload = bytes.fromhex(args.payload)
        for reply in querier.get(payload=payload, attachment=attachment(i, gid)):
            if reply.ok is not None:
                out("REPLY " + sample_json(reply.ok))
            else:
                out("REPLY_ERROR " + reply.err.payload.to_string())
    return 0


def cmd_serve(args):
    """A service server as rmw_zenoh's: a complete queryable on the service's key; each
    request {int64 a, int64 b} is answered with {int64 sum} on the same key, its attachment
    the request's sequence number and client GID."""
    s = session(args)
    answered = [0]
    done = threading.Event()

    def on_query(query):
        att = query.attachment
        if att is None:
            out("REQUEST_WITHOUT_ATTACHMENT")
            return
        seq, _ts, gid = attachment_fields(att)
        body = query.payload.to_bytes()
        a, b = struct.unpack("<qq", body[4:20])
        out(f"REQUEST {int(seq)} {a} {b} {bytes(gid).hex()}")
        reply = b"\x00\x01\x00\x00" + struct.pack("<q", a + b)
        query.reply(args.key, reply, attachment=attachment(int(seq), bytes(gid)))
        answered[0] += 1
        if answered[0] >= args.count:
            done.set()

    _q = s.declare_queryable(args.key, on_query, complete=True)
    out("READY")
    if not wait(time.monotonic() + args.timeout, done):
        print(f"TIMEOUT answered={answered[0]}", file=sys.stderr)
        return 3
    time.sleep(0.5)
    return 0


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    for name in ["router", "sub", "pub", "tokens", "call", "serve"]:
        c = sub.add_parser(name)
        c.add_argument("--connect", default=None)
        c.add_argument("--listen", action="append", default=None)
        c.add_argument(
            "--private-namespace",
            action="store_true",
            help="allow the addresses of a network namespace the test made (no real network)",
        )
        c.add_argument("--key", default="**")
        c.add_argument("--count", type=int, default=1)
        c.add_argument("--timeout", type=float, default=30.0)
        c.add_argument("--interval-ms", type=int, default=100)
        c.add_argument("--delay-ms", type=int, default=0)
        c.add_argument("--message", default="hello")
        c.add_argument("--payload", default="")
        c.add_argument("--transient-local", action="store_true")
    args = p.parse_args()
    for ep in [args.connect] + (args.listen or []):
        # Loopback only (or a test's own namespaces): the tests never reach past this host.
        local = ep and (ep.startswith("tcp/127.0.0.1:") or ep.startswith("tcp/[::1]:"))
        if ep and not local and not args.private_namespace:
            print(f"{ep}: only loopback endpoints", file=sys.stderr)
            return 2
    return {
        "router": cmd_router,
        "sub": cmd_sub,
        "pub": cmd_pub,
        "tokens": cmd_tokens,
        "call": cmd_call,
        "serve": cmd_serve,
    }[args.cmd](args)


if __name__ == "__main__":
    sys.exit(main())
