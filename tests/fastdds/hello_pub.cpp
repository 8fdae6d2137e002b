// Minimal Fast DDS 2.9 publisher: topic "HelloWorldTopic", type "HelloWorld".
#include "HelloWorldType.hpp"
#include "common.hpp"

#include <atomic>
#include <chrono>
#include <thread>
#include <fastdds/dds/domain/DomainParticipant.hpp>
#include <fastdds/dds/publisher/Publisher.hpp>
#include <fastdds/dds/publisher/DataWriter.hpp>
#include <fastdds/dds/publisher/DataWriterListener.hpp>
#include <fastdds/dds/publisher/qos/DataWriterQos.hpp>
#include <fastdds/dds/topic/Topic.hpp>
#include <fastdds/dds/topic/TypeSupport.hpp>

using namespace eprosima::fastdds::dds;

class WListener : public DataWriterListener
{
public:
    std::atomic<int> matched{0};
    void on_publication_matched(DataWriter*, const PublicationMatchedStatus& info) override
    {
        matched = info.current_count;
        std::fprintf(stderr, "[pub] publication matched: current_count=%d (change %d)\n",
                info.current_count, info.current_count_change);
    }
    void on_offered_incompatible_qos(DataWriter*, const OfferedIncompatibleQosStatus& s) override
    {
        std::fprintf(stderr, "[pub] offered incompatible QoS (last policy id %u)\n", s.last_policy_id);
    }
};

int main(int argc, char** argv)
{
    Options o = parse(argc, argv, false);
    std::fprintf(stderr, "[pub] domain=%d count=%d reliability=%s durability=%s transports=%s\n",
            o.domain, o.count, o.best_effort ? "BEST_EFFORT" : "RELIABLE",
            o.transient_local ? "TRANSIENT_LOCAL" : "VOLATILE",
            o.builtin_transports ? "builtin(UDPv4+SHM)" : (o.peers ? "UDPv4@127.0.0.1+peer" : "UDPv4@127.0.0.1"));

    auto* factory = DomainParticipantFactory::get_instance();
    DomainParticipant* participant = factory->create_participant(o.domain, participant_qos(o, "hello_pub"));
    if (!participant) { std::fprintf(stderr, "[pub] create_participant failed\n"); return 1; }

    TypeSupport type(new HelloWorldPubSubType());
    type.register_type(participant);
    Topic* topic = participant->create_topic("HelloWorldTopic", "HelloWorld", TOPIC_QOS_DEFAULT);
    Publisher* publisher = participant->create_publisher(PUBLISHER_QOS_DEFAULT);
    if (!topic || !publisher) { std::fprintf(stderr, "[pub] create topic/publisher failed\n"); return 1; }

    DataWriterQos wqos = DATAWRITER_QOS_DEFAULT;
    wqos.reliability().kind = o.best_effort ? BEST_EFFORT_RELIABILITY_QOS : RELIABLE_RELIABILITY_QOS;
    wqos.durability().kind = o.transient_local ? TRANSIENT_LOCAL_DURABILITY_QOS : VOLATILE_DURABILITY_QOS;
    wqos.history().kind = KEEP_LAST_HISTORY_QOS;
    wqos.history().depth = o.count < 1000 ? o.count : 1000;
    wqos.publish_mode().kind = SYNCHRONOUS_PUBLISH_MODE;

    WListener listener;
    DataWriter* writer = publisher->create_datawriter(topic, wqos, &listener);
    if (!writer) { std::fprintf(stderr, "[pub] create_datawriter failed\n"); return 1; }

    // wait up to 10 s for at least one matched reader
    auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(10);
    while (listener.matched < 1 && std::chrono::steady_clock::now() < deadline)
        std::this_thread::sleep_for(std::chrono::milliseconds(50));
    int rc = 0;
    if (listener.matched < 1)
    {
        std::fprintf(stderr, "[pub] no reader matched within 10 s, giving up\n");
        rc = 1;
    }
    else
    {
        // give the reader side a moment to finish matching our writer (reliable handshake)
        std::this_thread::sleep_for(std::chrono::milliseconds(200));
        HelloWorld sample;
        sample.message = "Hello DDS world!";
        for (int i = 1; i <= o.count; ++i)
        {
            sample.index = static_cast<uint32_t>(i);
            bool ok = writer->write(&sample);
            std::printf("sent index=%u message=%s%s\n", sample.index, sample.message.c_str(), ok ? "" : " (write FAILED)");
            std::fflush(stdout);
            if (!ok) rc = 1;
            std::this_thread::sleep_for(std::chrono::milliseconds(100));
        }
        if (!o.best_effort)
            writer->wait_for_acknowledgments(eprosima::fastrtps::Duration_t(5, 0));
        std::this_thread::sleep_for(std::chrono::milliseconds(300));
    }

    publisher->delete_datawriter(writer);
    participant->delete_publisher(publisher);
    participant->delete_topic(topic);
    factory->delete_participant(participant);
    return rc;
}
