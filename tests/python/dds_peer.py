#!/usr/bin/env python3
"""Independent DDS peer (Eclipse Cyclone DDS, Python binding) for end-to-end tests.

Subcommands:
  read  --count N                       print READY, then one JSON line per sample
  write --count N --interval-ms M ...   publish N HelloWorld samples
  graph --count N                       read ros_discovery_info (ROS 2 graph) and the DDS
                                        built-in publication/subscription topics
  --keyed (both)                        use the keyed ShapesDemoTypes::ShapeType {@key string
                                        color; long x, y, shapesize} instead of HelloWorld
  --ros-string (read, write)            use ROS 2's std_msgs/String (std_msgs::msg::dds_::String_
                                        {string data}), what micro-ROS's talker publishes; a
                                        sample's index is the number that ends its text

Output protocol (stdout, one line each, flushed):
  READY                  reader (read) / writer (write) exists
  MATCHED <n>            matched-endpoint count changed to n (n >= 1 for write --wait-match;
                         a writer reports changes before the next SENT)
  {"index": i, "message": "..."}   one received sample (read)
  {"color": c, "x": x, "state": "alive"|"disposed"|"no_writers"}   (read --keyed; disposes
                         and unregisters count as samples)
  DISPOSED <color>       instance disposed (write --keyed --dispose)
  GRAPH {"gid": hex, "nodes": [{"ns", "name", "writers": [hex], "readers": [hex]}]}
                         one ros_discovery_info sample (graph)
  ENDPOINT <pub|sub> <guid hex> <topic>   a discovered DDS endpoint (graph)
  SENT <i>               sample i written (write)
  ACKED                  every matched reliable reader acknowledged every sample (write)
On timeout: exit code 3 and a `TIMEOUT ...` line on stderr.
Usage errors / missing CYCLONEDDS_URI: exit code 2.

CYCLONEDDS_URI must be set (e.g. file:///.../cyclonedds-loopback.xml) so that
the peer never uses a non-loopback interface by accident.
"""

import argparse
import json
import os
import sys
import time
from dataclasses import dataclass

EXIT_OK = 0
EXIT_USAGE = 2
EXIT_TIMEOUT = 3


def eprint(*args):
    print(*args, file=sys.stderr, flush=True)


def out(line):
    print(line, flush=True)


def parse_args(argv):
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--domain", type=int, default=0, help="DDS domain id (default 0)")
    common.add_argument("--topic", default="HelloWorldTopic", help="topic name (default HelloWorldTopic)")
    rel = common.add_mutually_exclusive_group()
    rel.add_argument("--reliable", dest="reliable", action="store_true", default=True,
                     help="RELIABLE reliability (default)")
    rel.add_argument("--best-effort", dest="reliable", action="store_false",
                     help="BEST_EFFORT reliability")
    common.add_argument("--transient-local", action="store_true",
                        help="TRANSIENT_LOCAL durability (default VOLATILE)")
    common.add_argument("--timeout", type=float, default=30.0,
                        help="seconds before giving up (default 30)")
    common.add_argument("--partition", default="",
                        help="read or write in this partition (default: the default partition)")
    common.add_argument("--keyed", action="store_true",
                        help="keyed ShapeType samples instead of HelloWorld")
    common.add_argument("--ros-string", action="store_true",
                        help="std_msgs::msg::dds_::String_ samples instead of HelloWorld")
    common.add_argument("--history", type=int, default=0,
                        help="KEEP_LAST depth (default: KEEP_ALL for read, --count for write)")

    p = argparse.ArgumentParser(prog="dds_peer.py", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True)

    r = sub.add_parser("read", parents=[common], help="subscribe and print samples as JSON lines")
    r.add_argument("--count", type=int, default=1, help="samples to receive before exiting 0 (default 1)")
    r.add_argument("--linger-ms", type=int, default=1000,
                   help="after --count samples, keep printing what still arrives for this long "
                        "(a late duplicate shows; default 1000; HelloWorld only)")

    g = sub.add_parser("graph", parents=[common], help="print ros_discovery_info samples")
    g.add_argument("--count", type=int, default=1, help="graph samples to receive (default 1)")

    w = sub.add_parser("write", parents=[common], help="publish samples")
    w.add_argument("--count", type=int, default=1, help="samples to write (default 1)")
    w.add_argument("--interval-ms", type=int, default=100, help="pause between samples (default 100)")
    w.add_argument("--message", default="Hello DDS", help="message text of every sample")
    w.add_argument("--message-repeat", type=int, default=1,
                   help="repeat the message text this many times (large samples)")
    w.add_argument("--wait-match", action="store_true",
                   help="wait (up to --timeout) for at least one matched reader before writing")
    w.add_argument("--settle-ms", type=int, default=300,
                   help="with --wait-match: pause this long after the match (default 300): the "
                        "writer matching the reader does not mean the reader matched the writer, "
                        "and a volatile reader misses what was written before it did")
    w.add_argument("--linger-ms", type=int, default=1000,
                   help="stay alive this long after the last write (default 1000)")
    w.add_argument("--colors", default="RED,GREEN,BLUE",
                   help="keyed: colors written round robin, x = sample number")
    w.add_argument("--dispose", default="",
                   help="keyed: dispose the instance of this color after the writes")
    return p.parse_args(argv)


def main(argv=None):
    args = parse_args(sys.argv[1:] if argv is None else argv)

    uri = os.environ.get("CYCLONEDDS_URI", "").strip()
    if not uri:
        eprint("error: CYCLONEDDS_URI is not set; refusing to start Cyclone DDS with its default "
               "configuration (it could use a non-loopback interface). Set e.g. "
               "CYCLONEDDS_URI=file:///abs/path/cyclonedds-loopback.xml")
        return EXIT_USAGE
    if args.count < 0 or args.timeout <= 0:
        eprint("error: --count must be >= 0 and --timeout > 0")
        return EXIT_USAGE

    # Imported only after the environment check so that a missing URI never starts DDS.
    from cyclonedds.core import DDSStatus, InstanceState, ReadCondition, SampleState, ViewState, WaitSet
    from cyclonedds.domain import DomainParticipant
    from cyclonedds.idl import IdlStruct
    from cyclonedds.idl import annotations as annotate
    from cyclonedds.idl.types import int32, uint32
    from cyclonedds.pub import DataWriter
    from cyclonedds.qos import Policy, Qos
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic
    from cyclonedds.util import duration

    @dataclass
    @annotate.final
    class HelloWorld(IdlStruct, typename="HelloWorld"):
        index: uint32
        message: str

    @dataclass
    @annotate.final
    @annotate.keylist(["color"])
    class ShapeType(IdlStruct, typename="ShapesDemoTypes::ShapeType"):
        color: str
        x: int32
        y: int32
        shapesize: int32

    @dataclass
    @annotate.final
    class RosString(IdlStruct, typename="std_msgs::msg::dds_::String_"):
        data: str

    def as_hello(s):
        """A sample as the HelloWorld lines print it (a ROS string's index ends its text)."""
        if isinstance(s, HelloWorld):
            return s.index, s.message
        tail = s.data.rsplit(" ", 1)[-1]
        return (int(tail) if tail.isdigit() else -1), s.data

    start = time.monotonic()
    deadline = start + args.timeout

    def remaining_ns():
        return max(0, int((deadline - time.monotonic()) * 1e9))

    policies = [
        Policy.Reliability.Reliable(max_blocking_time=duration(seconds=1))
        if args.reliable else Policy.Reliability.BestEffort,
        Policy.Durability.TransientLocal if args.transient_local else Policy.Durability.Volatile,
    ]

    dp = DomainParticipant(args.domain)
    if args.cmd == "graph":
        return graph(args, dp, remaining_ns)
    if args.keyed and args.ros_string:
        eprint("error: --keyed and --ros-string exclude each other")
        return EXIT_USAGE
    sample_type = ShapeType if args.keyed else RosString if args.ros_string else HelloWorld
    topic = Topic(dp, args.topic, sample_type)
    waitset = WaitSet(dp)

    if args.cmd == "read":
        qos = Qos(*policies,
                  Policy.History.KeepLast(args.history) if args.history > 0
                  else Policy.History.KeepAll,
                  # Accept both XCDR1 and XCDR2 writers.
                  Policy.DataRepresentation(use_cdrv0_representation=True,
                                            use_xcdrv2_representation=True))
        if args.partition:
            from cyclonedds.sub import Subscriber
            sub = Subscriber(dp, qos=Qos(Policy.Partition(partitions=[args.partition])))
            reader = DataReader(sub, topic, qos=qos)
        else:
            reader = DataReader(dp, topic, qos=qos)
        # The reader entity itself is a status condition triggered by the masked statuses.
        reader.set_status_mask(DDSStatus.SubscriptionMatched)
        cond = ReadCondition(reader, SampleState.Any | ViewState.Any | InstanceState.Any)
        waitset.attach(cond)
        waitset.attach(reader)
        out("READY")

        got = 0
        last_matched = 0
        while got < args.count:
            if reader.get_status_changes() & DDSStatus.SubscriptionMatched:
                st = reader.get_subscription_matched_status()  # also resets the change flag
                if st.current_count != last_matched:
                    last_matched = st.current_count
                    out(f"MATCHED {last_matched}")
            for s in reader.take(N=64, condition=cond):
                if args.keyed:
                    # A valid sample carries its instance's state at take time too (a
                    # dispose that arrives before the take is not a separate sample).
                    st = s.sample_info.instance_state
                    state = ("alive" if st == InstanceState.Alive
                             else "disposed" if st == InstanceState.NotAliveDisposed
                             else "no_writers")
                    if isinstance(s, ShapeType):
                        out(json.dumps({"color": s.color, "x": int(s.x), "state": state}))
                    else:
                        key = getattr(s.key_sample, "color", None)
                        out(json.dumps({"color": key, "x": None, "state": state}))
                    got += 1
                    if got >= args.count:
                        break
                    continue
                if not isinstance(s, (HelloWorld, RosString)):  # invalid (dispose, no writers)
                    continue
                index, message = as_hello(s)
                out(json.dumps({"index": int(index), "message": message,
                                "writer": int(s.sample_info.publication_handle)}))
                got += 1
                if got >= args.count:
                    break
            if got >= args.count:
                break
            left = remaining_ns()
            if left == 0:
                eprint(f"TIMEOUT got={got}")
                return EXIT_TIMEOUT
            waitset.wait(left)
        # Past the count, what still arrives is printed too for a while: a test that expects
        # exactly N samples must see an (N+1)th, a late duplicate, rather than a peer gone.
        if not args.keyed and args.linger_ms > 0:
            linger_end = time.monotonic() + args.linger_ms / 1000.0
            while True:
                for s in reader.take(N=64, condition=cond):
                    if isinstance(s, (HelloWorld, RosString)):
                        index, message = as_hello(s)
                        out(json.dumps({"index": int(index), "message": message,
                                        "writer": int(s.sample_info.publication_handle)}))
                left = linger_end - time.monotonic()
                if left <= 0:
                    break
                waitset.wait(int(left * 1e9))
        return EXIT_OK

    # write
    depth = args.history if args.history > 0 else max(1, args.count)
    qos = Qos(*policies,
              Policy.History.KeepLast(depth),
              # Cyclone sizes the TRANSIENT_LOCAL history kept for late joiners from the
              # DurabilityService history (default KEEP_LAST 1), not from History.
              Policy.DurabilityService(cleanup_delay=0, history=Policy.History.KeepLast(depth),
                                       max_samples=-1, max_instances=-1,
                                       max_samples_per_instance=-1),
              Policy.DataRepresentation(use_cdrv0_representation=True))  # XCDR1 on the wire
    writer = DataWriter(dp, topic, qos=qos)
    writer.set_status_mask(DDSStatus.PublicationMatched)
    waitset.attach(writer)
    out("READY")

    last_matched = None
    if args.wait_match:
        while True:
            st = writer.get_publication_matched_status()
            if st.current_count >= 1:
                out(f"MATCHED {st.current_count}")
                last_matched = st.current_count
                time.sleep(args.settle_ms / 1000.0)
                break
            left = remaining_ns()
            if left == 0:
                eprint("TIMEOUT no matching reader")
                return EXIT_TIMEOUT
            waitset.wait(left)

    for i in range(args.count):
        if i > 0 and args.interval_ms > 0:
            time.sleep(args.interval_ms / 1000.0)
        # A change of the match count is reported before the next sample, so that a test
        # knows which samples were written while a reader was matched.
        matched = writer.get_publication_matched_status().current_count
        if matched != last_matched:
            out(f"MATCHED {matched}")
            last_matched = matched
        if args.keyed:
            colors = args.colors.split(",")
            writer.write(ShapeType(color=colors[i % len(colors)], x=i, y=2 * i, shapesize=30))
        elif args.ros_string:
            writer.write(RosString(data=f"{args.message * args.message_repeat} {i}"))
        else:
            writer.write(HelloWorld(index=i, message=args.message * args.message_repeat))
        out(f"SENT {i}")
    if args.keyed and args.dispose:
        writer.dispose(ShapeType(color=args.dispose, x=0, y=0, shapesize=0))
        out(f"DISPOSED {args.dispose}")

    # Every matched reliable reader has every sample (the tests wait for this line instead
    # of sleeping).
    if args.reliable and writer.wait_for_acks(duration(seconds=10)):
        out("ACKED")
    if args.linger_ms > 0:
        time.sleep(args.linger_ms / 1000.0)
    return EXIT_OK


def graph(args, dp, remaining_ns):
    """Prints each ros_discovery_info sample and every discovered DDS endpoint."""
    from cyclonedds.builtin import (BuiltinDataReader, BuiltinTopicDcpsPublication,
                                    BuiltinTopicDcpsSubscription)
    from cyclonedds.core import WaitSet, ReadCondition, SampleState, ViewState, InstanceState
    from cyclonedds.idl import IdlStruct
    from cyclonedds.idl import annotations as annotate
    from cyclonedds.idl import types
    from cyclonedds.qos import Policy, Qos
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic

    @dataclass
    @annotate.final
    class Gid(IdlStruct, typename="rmw_dds_common::msg::dds_::Gid_"):
        data: types.array[types.uint8, 16]

    @dataclass
    @annotate.final
    class NodeEntitiesInfo(IdlStruct, typename="rmw_dds_common::msg::dds_::NodeEntitiesInfo_"):
        node_namespace: str
        node_name: str
        reader_gid_seq: types.sequence[Gid]
        writer_gid_seq: types.sequence[Gid]

    @dataclass
    @annotate.final
    class ParticipantEntitiesInfo(IdlStruct,
                                  typename="rmw_dds_common::msg::dds_::ParticipantEntitiesInfo_"):
        gid: Gid
        node_entities_info_seq: types.sequence[NodeEntitiesInfo]

    topic = Topic(dp, "ros_discovery_info", ParticipantEntitiesInfo)
    qos = Qos(Policy.Reliability.Reliable(max_blocking_time=0),
              Policy.Durability.TransientLocal, Policy.History.KeepLast(1),
              Policy.DataRepresentation(use_cdrv0_representation=True,
                                        use_xcdrv2_representation=True))
    reader = DataReader(dp, topic, qos=qos)
    pubs = BuiltinDataReader(dp, BuiltinTopicDcpsPublication)
    subs = BuiltinDataReader(dp, BuiltinTopicDcpsSubscription)
    waitset = WaitSet(dp)
    any_state = SampleState.Any | ViewState.Any | InstanceState.Any
    conds = [ReadCondition(r, any_state) for r in (reader, pubs, subs)]
    for c in conds:
        waitset.attach(c)
    out("READY")

    def hexgid(g):
        return bytes(g.data).hex()

    got = 0
    while got < args.count:
        for kind, r, c in (("pub", pubs, conds[1]), ("sub", subs, conds[2])):
            for e in r.take(N=64, condition=c):
                topic_name = getattr(e, "topic_name", None)
                if topic_name is not None:
                    out(f"ENDPOINT {kind} {e.key.bytes.hex()} {topic_name}")
        for s in reader.take(N=16, condition=conds[0]):
            if not isinstance(s, ParticipantEntitiesInfo):
                continue
            nodes = [{"ns": n.node_namespace, "name": n.node_name,
                      "writers": [hexgid(g) for g in n.writer_gid_seq],
                      "readers": [hexgid(g) for g in n.reader_gid_seq]}
                     for n in s.node_entities_info_seq]
            out("GRAPH " + json.dumps({"gid": hexgid(s.gid), "nodes": nodes}))
            got += 1
        if got >= args.count:
            break
        left = remaining_ns()
        if left == 0:
            eprint(f"TIMEOUT got={got}")
            return EXIT_TIMEOUT
        waitset.wait(min(left, 100_000_000))
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
