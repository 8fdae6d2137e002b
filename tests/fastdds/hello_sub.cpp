// Minimal Fast DDS 2.9 subscriber: topic "HelloWorldTopic", type "HelloWorld".
#include "HelloWorldType.hpp"
#include "common.hpp"

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <mutex>
#include <thread>
#include <fastdds/dds/domain/DomainParticipant.hpp>
#include <fastdds/dds/subscriber/Subscriber.hpp>
#include <fastdds/dds/subscriber/DataReader.hpp>
#include <fastdds/dds/subscriber/DataReaderListener.hpp>
#include <fastdds/dds/subscriber/SampleInfo.hpp>
#include <fastdds/dds/subscriber/qos/DataReaderQos.hpp>
#include <fastdds/dds/topic/Topic.hpp>
#include <fastdds/dds/topic/TypeSupport.hpp>

using namespace eprosima::fastdds::dds;

class RListener : public DataReaderListener
{
public:
    int target = 10;
    int received = 0;
    std::mutex m;
    std::condition_variable cv;

    void on_subscription_matched(DataReader*, const SubscriptionMatchedStatus& info) override
    {
        std::fprintf(stderr, "[sub] subscription matched: current_count=%d (change %d)\n",
                info.current_count, info.current_count_change);
    }
    void on_requested_incompatible_qos(DataReader*, const RequestedIncompatibleQosStatus& s) override
    {
        std::fprintf(stderr, "[sub] requested incompatible QoS (last policy id %u)\n", s.last_policy_id);
    }
    void on_data_available(DataReader* reader) override
    {
        HelloWorld sample;
        SampleInfo info;
        while (reader->take_next_sample(&sample, &info) == ReturnCode_t::RETCODE_OK)
        {
            if (!info.valid_data) continue;
            std::printf("index=%u message=%s\n", sample.index, sample.message.c_str());
            std::fflush(stdout);
            std::lock_guard<std::mutex> lk(m);
            ++received;
            cv.notify_all();
        }
    }
};

int main(int argc, char** argv)
{
    Options o = parse(argc, argv, true);
    std::fprintf(stderr, "[sub] domain=%d count=%d timeout=%ds reliability=%s durability=%s transports=%s\n",
            o.domain, o.count, o.timeout_s, o.best_effort ? "BEST_EFFORT" : "RELIABLE",
            o.transient_local ? "TRANSIENT_LOCAL" : "VOLATILE",
            o.builtin_transports ? "builtin(UDPv4+SHM)" : (o.peers ? "UDPv4@127.0.0.1+peer" : "UDPv4@127.0.0.1"));

    auto* factory = DomainParticipantFactory::get_instance();
    DomainParticipant* participant = factory->create_participant(o.domain, participant_qos(o, "hello_sub"));
    if (!participant) { std::fprintf(stderr, "[sub] create_participant failed\n"); return 1; }

    TypeSupport type(new HelloWorldPubSubType());
    type.register_type(participant);
    Topic* topic = participant->create_topic("HelloWorldTopic", "HelloWorld", TOPIC_QOS_DEFAULT);
    Subscriber* subscriber = participant->create_subscriber(SUBSCRIBER_QOS_DEFAULT);
    if (!topic || !subscriber) { std::fprintf(stderr, "[sub] create topic/subscriber failed\n"); return 1; }

    DataReaderQos rqos = DATAREADER_QOS_DEFAULT;
    rqos.reliability().kind = o.best_effort ? BEST_EFFORT_RELIABILITY_QOS : RELIABLE_RELIABILITY_QOS;
    rqos.durability().kind = o.transient_local ? TRANSIENT_LOCAL_DURABILITY_QOS : VOLATILE_DURABILITY_QOS;
    rqos.history().kind = KEEP_LAST_HISTORY_QOS;
    rqos.history().depth = o.count < 1000 ? o.count : 1000;

    RListener listener;
    listener.target = o.count;
    DataReader* reader = subscriber->create_datareader(topic, rqos, &listener);
    if (!reader) { std::fprintf(stderr, "[sub] create_datareader failed\n"); return 1; }

    int got;
    {
        std::unique_lock<std::mutex> lk(listener.m);
        listener.cv.wait_for(lk, std::chrono::seconds(o.timeout_s), [&] { return listener.received >= o.count; });
        got = listener.received;
    }
    if (got >= o.count)
    {
        // Listening on past the count, so that a sample delivered twice is printed twice.
        std::this_thread::sleep_for(std::chrono::milliseconds(o.linger_ms));
        std::lock_guard<std::mutex> lk(listener.m);
        got = listener.received;
    }
    std::fprintf(stderr, "[sub] received %d/%d samples\n", got, o.count);

    reader->set_listener(nullptr);
    subscriber->delete_datareader(reader);
    participant->delete_subscriber(subscriber);
    participant->delete_topic(topic);
    factory->delete_participant(participant);
    return got >= o.count ? 0 : 1;
}
