// Minimal Fast DDS 2.9 replier for the tests' adder service, written as eProsima's agent
// serves XRCE repliers: requests on "rq/addRequest" (type AddRequest { a, b }), each answered
// on "rr/addReply" (type AddReply { sum }) with the request's SampleIdentity as the reply's
// related sample identity, which is how the requester finds its reply.
// Prints "request seq=<high>.<low> a=<a> b=<b>" per request taken; exits 0 after -n requests
// and a second more (a request delivered twice would show), 1 on timeout.
#include "common.hpp"

#include <chrono>
#include <condition_variable>
#include <mutex>
#include <thread>
#include <fastcdr/Cdr.h>
#include <fastdds/dds/domain/DomainParticipant.hpp>
#include <fastcdr/FastBuffer.h>
#include <fastcdr/exceptions/Exception.h>
#include <fastdds/dds/publisher/DataWriter.hpp>
#include <fastdds/dds/publisher/Publisher.hpp>
#include <fastdds/dds/publisher/qos/DataWriterQos.hpp>
#include <fastdds/dds/subscriber/DataReader.hpp>
#include <fastdds/dds/subscriber/DataReaderListener.hpp>
#include <fastdds/dds/subscriber/SampleInfo.hpp>
#include <fastdds/dds/subscriber/Subscriber.hpp>
#include <fastdds/dds/subscriber/qos/DataReaderQos.hpp>
#include <fastdds/dds/topic/Topic.hpp>
#include <fastdds/dds/topic/TopicDataType.hpp>
#include <fastdds/dds/topic/TypeSupport.hpp>
#include <fastrtps/rtps/common/WriteParams.h>

using namespace eprosima::fastdds::dds;

// A struct of unsigned longs, plain CDR (XCDR1) with its encapsulation header, no key.
template <int N>
struct Longs
{
    uint32_t v[N] = {};
};

template <int N>
class LongsType : public TopicDataType
{
public:
    explicit LongsType(const char* name)
    {
        setName(name);
        m_typeSize = 4 + 4 * N;
        m_isGetKeyDefined = false;
        auto_fill_type_object(false);
        auto_fill_type_information(false);
    }

    bool serialize(void* data, eprosima::fastrtps::rtps::SerializedPayload_t* payload) override
    {
        auto* p = static_cast<Longs<N>*>(data);
        eprosima::fastcdr::FastBuffer fb(reinterpret_cast<char*>(payload->data), payload->max_size);
        eprosima::fastcdr::Cdr ser(fb, eprosima::fastcdr::Cdr::DEFAULT_ENDIAN, eprosima::fastcdr::Cdr::DDS_CDR);
        payload->encapsulation = ser.endianness() == eprosima::fastcdr::Cdr::BIG_ENDIANNESS ? CDR_BE : CDR_LE;
        try
        {
            ser.serialize_encapsulation();
            for (int i = 0; i < N; ++i) ser.serialize(p->v[i]);
        }
        catch (eprosima::fastcdr::exception::Exception&)
        {
            return false;
        }
        payload->length = static_cast<uint32_t>(ser.getSerializedDataLength());
        return true;
    }

    bool deserialize(eprosima::fastrtps::rtps::SerializedPayload_t* payload, void* data) override
    {
        auto* p = static_cast<Longs<N>*>(data);
        eprosima::fastcdr::FastBuffer fb(reinterpret_cast<char*>(payload->data), payload->length);
        eprosima::fastcdr::Cdr deser(fb, eprosima::fastcdr::Cdr::DEFAULT_ENDIAN, eprosima::fastcdr::Cdr::DDS_CDR);
        try
        {
            deser.read_encapsulation();
            payload->encapsulation = deser.endianness() == eprosima::fastcdr::Cdr::BIG_ENDIANNESS ? CDR_BE : CDR_LE;
            for (int i = 0; i < N; ++i) deser.deserialize(p->v[i]);
        }
        catch (eprosima::fastcdr::exception::Exception&)
        {
            return false;
        }
        return true;
    }

    std::function<uint32_t()> getSerializedSizeProvider(void*) override
    {
        return []() -> uint32_t { return 4 + 4 * N; };
    }

    void* createData() override { return new Longs<N>(); }
    void deleteData(void* data) override { delete static_cast<Longs<N>*>(data); }
    bool getKey(void*, eprosima::fastrtps::rtps::InstanceHandle_t*, bool = false) override { return false; }
};

class Replier : public DataReaderListener
{
public:
    DataWriter* writer = nullptr;
    int answered = 0;
    std::mutex m;
    std::condition_variable cv;

    void on_subscription_matched(DataReader*, const SubscriptionMatchedStatus& info) override
    {
        std::fprintf(stderr, "[replier] requests matched: current_count=%d\n", info.current_count);
    }
    void on_data_available(DataReader* reader) override
    {
        Longs<2> request;
        SampleInfo info;
        while (reader->take_next_sample(&request, &info) == ReturnCode_t::RETCODE_OK)
        {
            if (!info.valid_data) continue;
            const auto& seq = info.sample_identity.sequence_number();
            std::printf("request seq=%d.%u a=%u b=%u\n", seq.high, seq.low, request.v[0], request.v[1]);
            std::fflush(stdout);
            Longs<1> reply;
            reply.v[0] = request.v[0] + request.v[1];
            eprosima::fastrtps::rtps::WriteParams params;
            params.related_sample_identity(info.sample_identity);
            if (!writer->write(&reply, params))
            {
                std::fprintf(stderr, "[replier] writing a reply failed\n");
            }
            std::lock_guard<std::mutex> lk(m);
            ++answered;
            cv.notify_all();
        }
    }
};

int main(int argc, char** argv)
{
    Options o = parse(argc, argv, true);
    auto* factory = DomainParticipantFactory::get_instance();
    DomainParticipant* participant = factory->create_participant(o.domain, participant_qos(o, "adder_replier"));
    if (!participant) { std::fprintf(stderr, "[replier] create_participant failed\n"); return 1; }
    TypeSupport request_type(new LongsType<2>("AddRequest"));
    TypeSupport reply_type(new LongsType<1>("AddReply"));
    request_type.register_type(participant);
    reply_type.register_type(participant);
    Topic* requests = participant->create_topic("rq/addRequest", "AddRequest", TOPIC_QOS_DEFAULT);
    Topic* replies = participant->create_topic("rr/addReply", "AddReply", TOPIC_QOS_DEFAULT);
    Subscriber* subscriber = participant->create_subscriber(SUBSCRIBER_QOS_DEFAULT);
    Publisher* publisher = participant->create_publisher(PUBLISHER_QOS_DEFAULT);
    if (!requests || !replies || !subscriber || !publisher) { std::fprintf(stderr, "[replier] create entities failed\n"); return 1; }

    DataWriterQos wqos = DATAWRITER_QOS_DEFAULT;
    wqos.reliability().kind = RELIABLE_RELIABILITY_QOS;
    wqos.durability().kind = VOLATILE_DURABILITY_QOS;
    Replier replier;
    replier.writer = publisher->create_datawriter(replies, wqos);
    DataReaderQos rqos = DATAREADER_QOS_DEFAULT;
    rqos.reliability().kind = RELIABLE_RELIABILITY_QOS;
    rqos.durability().kind = VOLATILE_DURABILITY_QOS;
    DataReader* reader = subscriber->create_datareader(requests, rqos, &replier);
    if (!replier.writer || !reader) { std::fprintf(stderr, "[replier] create reader/writer failed\n"); return 1; }
    std::fprintf(stderr, "[replier] serving rq/addRequest in domain %d\n", o.domain);

    int got;
    {
        std::unique_lock<std::mutex> lk(replier.m);
        replier.cv.wait_for(lk, std::chrono::seconds(o.timeout_s), [&] { return replier.answered >= o.count; });
    }
    // A second more: a request delivered twice shows as a second line.
    std::this_thread::sleep_for(std::chrono::seconds(1));
    {
        std::lock_guard<std::mutex> lk(replier.m);
        got = replier.answered;
    }
    std::fprintf(stderr, "[replier] answered %d/%d requests\n", got, o.count);
    reader->set_listener(nullptr);
    subscriber->delete_datareader(reader);
    publisher->delete_datawriter(replier.writer);
    participant->delete_subscriber(subscriber);
    participant->delete_publisher(publisher);
    participant->delete_topic(requests);
    participant->delete_topic(replies);
    factory->delete_participant(participant);
    return got >= o.count ? 0 : 1;
}
