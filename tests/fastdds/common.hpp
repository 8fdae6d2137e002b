// Shared CLI + participant setup for hello_pub / hello_sub.
#pragma once
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <string>
#include <fastdds/dds/domain/DomainParticipantFactory.hpp>
#include <fastdds/dds/domain/qos/DomainParticipantQos.hpp>
#include <fastdds/rtps/transport/UDPv4TransportDescriptor.h>
#include <fastrtps/utils/IPLocator.h>

struct Options
{
    int domain = 0;
    int count = 10;
    int timeout_s = 20;        // subscriber only
    int linger_ms = 1000;      // subscriber only: listens this long after -n samples
    bool best_effort = false;  // default RELIABLE
    bool transient_local = false; // default VOLATILE
    bool builtin_transports = false; // default: UDPv4 only, whitelist 127.0.0.1
    bool peers = true;         // add 127.0.0.1 initial peer (unicast discovery) in loopback mode
};

inline void usage(const char* prog, bool sub)
{
    std::fprintf(stderr,
            "usage: %s [-d|--domain N] [-n|--count N]%s [--best-effort|--reliable] [--transient-local|--volatile]\n"
            "          [--builtin-transports] [--no-peers]\n"
            "  defaults: domain 0, count 10%s, RELIABLE + VOLATILE, UDPv4 transport whitelisted to 127.0.0.1,\n"
            "            multicast discovery + initial peer 127.0.0.1\n"
            "  --best-effort        BEST_EFFORT reliability (matches the XRCE client's default best-effort reader)\n"
            "  --transient-local    TRANSIENT_LOCAL durability\n"
            "  --builtin-transports use Fast DDS default transports (UDPv4 on all interfaces + SHM), no whitelist\n"
            "  --no-peers           do not add the 127.0.0.1 initial peer (multicast discovery only)\n",
            prog, sub ? " [-t|--timeout SEC] [--linger-ms MS]" : "", sub ? ", timeout 20 s, linger 1000 ms" : "");
}

inline Options parse(int argc, char** argv, bool sub)
{
    Options o;
    for (int i = 1; i < argc; ++i)
    {
        std::string a = argv[i];
        auto next = [&]() -> int {
                if (i + 1 >= argc) { usage(argv[0], sub); std::exit(2); }
                return std::atoi(argv[++i]);
            };
        if (a == "-d" || a == "--domain") o.domain = next();
        else if (a == "-n" || a == "--count") o.count = next();
        else if (sub && (a == "-t" || a == "--timeout")) o.timeout_s = next();
        else if (sub && a == "--linger-ms") o.linger_ms = next();
        else if (a == "--best-effort") o.best_effort = true;
        else if (a == "--reliable") o.best_effort = false;
        else if (a == "--transient-local") o.transient_local = true;
        else if (a == "--volatile") o.transient_local = false;
        else if (a == "--builtin-transports") o.builtin_transports = true;
        else if (a == "--no-peers") o.peers = false;
        else { usage(argv[0], sub); std::exit(a == "-h" || a == "--help" ? 0 : 2); }
    }
    if (o.count < 1) o.count = 1;
    return o;
}

inline eprosima::fastdds::dds::DomainParticipantQos participant_qos(const Options& o, const char* name)
{
    using namespace eprosima::fastdds::dds;
    DomainParticipantQos pqos = PARTICIPANT_QOS_DEFAULT;
    pqos.name(name);
    if (!o.builtin_transports)
    {
        auto udp = std::make_shared<eprosima::fastdds::rtps::UDPv4TransportDescriptor>();
        udp->interfaceWhiteList.emplace_back("127.0.0.1");
        pqos.transport().use_builtin_transports = false;   // no SHM, no default UDPv4
        pqos.transport().user_transports.push_back(udp);
        // unicast metatraffic + user traffic on 127.0.0.1 (ports chosen by Fast DDS from the domain id)
        eprosima::fastrtps::rtps::Locator_t meta;
        meta.kind = LOCATOR_KIND_UDPv4;
        eprosima::fastrtps::rtps::IPLocator::setIPv4(meta, 127, 0, 0, 1);
        pqos.wire_protocol().builtin.metatrafficUnicastLocatorList.push_back(meta);
        pqos.wire_protocol().default_unicast_locator_list.push_back(meta);
        // keep standard SPDP multicast discovery too (239.255.0.1, port 7400 + 250*domain), joined on 127.0.0.1
        eprosima::fastrtps::rtps::Locator_t mcast;
        mcast.kind = LOCATOR_KIND_UDPv4;
        eprosima::fastrtps::rtps::IPLocator::setIPv4(mcast, 239, 255, 0, 1);
        pqos.wire_protocol().builtin.metatrafficMulticastLocatorList.push_back(mcast);
        if (o.peers)
        {
            eprosima::fastrtps::rtps::Locator_t peer;
            peer.kind = LOCATOR_KIND_UDPv4;
            eprosima::fastrtps::rtps::IPLocator::setIPv4(peer, 127, 0, 0, 1);
            // no port -> Fast DDS probes the well-known metatraffic unicast ports of the first participant ids
            pqos.wire_protocol().builtin.initialPeersList.push_back(peer);
        }
    }
    return pqos;
}
