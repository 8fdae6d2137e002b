#!/usr/bin/env python3
"""Independent decoder of ros_discovery_info in one ROS 2 layout (Cyclone DDS, Python).

rmw_dds_common's ParticipantEntitiesInfo, as ROS 2 defines it (msg/*.msg):

  Gid:                     char[24] data   (Humble)  |  char[16] data   (Iron and later)
  NodeEntitiesInfo:        string<=256 node_namespace, string<=256 node_name,
                           Gid[] reader_gid_seq, Gid[] writer_gid_seq
  ParticipantEntitiesInfo: Gid gid, NodeEntitiesInfo[] node_entities_info_seq

This script defines those types with cyclonedds.idl in the layout --layout names (humble:
24-octet Gids; jazzy: 16-octet Gids, as iron, kilted and rolling), subscribes to
ros_discovery_info in --domain as a ROS 2 reader would (reliable, transient-local, keep last
1), and prints what it decodes. It shares no code with the agent: it is the independent
reader the end-to-end test tests/tests/e2e/ros_graph_layouts.rs compares the agent against.
One layout per process: the two layouts have the same type names, which one participant
could not hold at once.

Usage:  ros_graph_layouts.py --layout humble|jazzy [--domain N] [--timeout S]

Output (stdout, one line each, flushed):
  READY <layout> <gid octets>       the reader exists
  GRAPH {"layout", "gid": hex, "nodes": [{"ns", "name", "readers": [hex], "writers": [hex]}]}
                                    one sample decoded in this layout
  PARSE_FAILED {"layout", "error"}  one sample this layout could not decode in Python
Cyclone DDS checks a sample against the reader's type before Python sees it: a sample that
cannot be read with this layout is usually dropped there, with a log line on stderr
("... deserialization ros_discovery_info/...ParticipantEntitiesInfo_ failed ..."), which the
test counts as a parse failure too. Some samples of the other layout do parse (a Humble
message read with 16-octet Gids is a Gid and an empty node list: the count read is Humble's
zero padding), so a decoder of the wrong layout never shows the node but may print a GRAPH.
Runs until --timeout (default 30 s), then exits 0 if it printed a GRAPH or PARSE_FAILED
line, 3 otherwise. Usage errors or CYCLONEDDS_URI unset: exit code 2 (the URI keeps DDS on
loopback, tests/python/cyclonedds-loopback.xml, as for dds_peer.py).
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

# Octets of a Gid in each layout.
GID_OCTETS = {"humble": 24, "jazzy": 16}


def out(line):
    print(line, flush=True)


def eprint(*args):
    print(*args, file=sys.stderr, flush=True)


def types_for(gid_octets):
    """The rmw_dds_common types with Gids of gid_octets octets."""
    from cyclonedds.idl import IdlStruct
    from cyclonedds.idl import annotations as annotate
    from cyclonedds.idl import types

    @dataclass
    @annotate.final
    class Gid(IdlStruct, typename="rmw_dds_common::msg::dds_::Gid_"):
        data: types.array[types.uint8, gid_octets]

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

    return ParticipantEntitiesInfo


def main(argv=None):
    p = argparse.ArgumentParser(prog="ros_graph_layouts.py", description=__doc__.splitlines()[0])
    p.add_argument("--layout", required=True, choices=sorted(GID_OCTETS),
                   help="humble (24-octet Gids) or jazzy (16-octet Gids)")
    p.add_argument("--domain", type=int, default=0, help="DDS domain id (default 0)")
    p.add_argument("--timeout", type=float, default=30.0, help="seconds to listen (default 30)")
    args = p.parse_args(sys.argv[1:] if argv is None else argv)
    if args.timeout <= 0:
        eprint("error: --timeout must be > 0")
        return EXIT_USAGE
    if not os.environ.get("CYCLONEDDS_URI", "").strip():
        eprint("error: CYCLONEDDS_URI is not set; refusing to start Cyclone DDS with its default "
               "configuration (it could use a non-loopback interface)")
        return EXIT_USAGE

    # Imported only after the checks so that a missing URI never starts DDS.
    from cyclonedds.core import InstanceState, ReadCondition, SampleState, ViewState, WaitSet
    from cyclonedds.domain import DomainParticipant
    from cyclonedds.qos import Policy, Qos
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic

    octets = GID_OCTETS[args.layout]
    info_type = types_for(octets)
    dp = DomainParticipant(args.domain)
    topic = Topic(dp, "ros_discovery_info", info_type)
    qos = Qos(Policy.Reliability.Reliable(max_blocking_time=0),
              Policy.Durability.TransientLocal, Policy.History.KeepLast(1),
              Policy.DataRepresentation(use_cdrv0_representation=True,
                                        use_xcdrv2_representation=True))
    reader = DataReader(dp, topic, qos=qos)
    cond = ReadCondition(reader, SampleState.Any | ViewState.Any | InstanceState.Any)
    waitset = WaitSet(dp)
    waitset.attach(cond)
    out(f"READY {args.layout} {octets}")

    deadline = time.monotonic() + args.timeout
    printed = 0
    while True:
        # One sample per take: the binding deserializes after taking, so a sample this
        # layout cannot decode raises here, alone (it is gone from the reader then), and is
        # reported as such. At most 64 failures per wake-up, should one ever repeat.
        failures = 0
        while failures < 64:
            try:
                samples = reader.take(N=1, condition=cond)
            except Exception as e:  # noqa: BLE001 - any decoding failure is the finding
                out("PARSE_FAILED " + json.dumps({"layout": args.layout,
                                                   "error": f"{type(e).__name__}: {e}"}))
                printed += 1
                failures += 1
                continue
            if not samples:
                break
            for s in samples:
                if not isinstance(s, info_type):
                    continue  # an unregister/dispose notification: no data
                nodes = [{"ns": n.node_namespace, "name": n.node_name,
                          "readers": [bytes(g.data).hex() for g in n.reader_gid_seq],
                          "writers": [bytes(g.data).hex() for g in n.writer_gid_seq]}
                         for n in s.node_entities_info_seq]
                out("GRAPH " + json.dumps({"layout": args.layout, "gid": bytes(s.gid.data).hex(),
                                           "nodes": nodes}))
                printed += 1
        left = deadline - time.monotonic()
        if left <= 0:
            break
        waitset.wait(int(min(left, 0.1) * 1e9))
    if printed == 0:
        eprint("TIMEOUT nothing received")
        return EXIT_TIMEOUT
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
