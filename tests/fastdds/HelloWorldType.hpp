// Hand-written TopicDataType for IDL:
//   struct HelloWorld { unsigned long index; string message; };
// Plain CDR (XCDR1) with 4-byte encapsulation header (CDR_LE/CDR_BE), no key.
#pragma once
#include <cstdint>
#include <string>
#include <fastdds/dds/topic/TopicDataType.hpp>
#include <fastcdr/FastBuffer.h>
#include <fastcdr/Cdr.h>
#include <fastcdr/exceptions/Exception.h>

struct HelloWorld
{
    uint32_t index = 0;
    std::string message;
};

class HelloWorldPubSubType : public eprosima::fastdds::dds::TopicDataType
{
public:
    // message bounded to 255 chars in practice (XRCE example uses char[255]); buffer sized accordingly
    static constexpr uint32_t kMaxMessage = 255;

    HelloWorldPubSubType()
    {
        setName("HelloWorld");
        // encapsulation(4) + index(4) + string length(4) + chars(255) + NUL(1)
        m_typeSize = 4 + 4 + 4 + kMaxMessage + 1;
        m_isGetKeyDefined = false;
        auto_fill_type_object(false);
        auto_fill_type_information(false);
    }

    bool serialize(void* data, eprosima::fastrtps::rtps::SerializedPayload_t* payload) override
    {
        HelloWorld* p = static_cast<HelloWorld*>(data);
        eprosima::fastcdr::FastBuffer fb(reinterpret_cast<char*>(payload->data), payload->max_size);
        eprosima::fastcdr::Cdr ser(fb, eprosima::fastcdr::Cdr::DEFAULT_ENDIAN, eprosima::fastcdr::Cdr::DDS_CDR);
        payload->encapsulation = ser.endianness() == eprosima::fastcdr::Cdr::BIG_ENDIANNESS ? CDR_BE : CDR_LE;
        try
        {
            ser.serialize_encapsulation();
            ser.serialize(p->index);
            ser.serialize(p->message);
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
        HelloWorld* p = static_cast<HelloWorld*>(data);
        eprosima::fastcdr::FastBuffer fb(reinterpret_cast<char*>(payload->data), payload->length);
        eprosima::fastcdr::Cdr deser(fb, eprosima::fastcdr::Cdr::DEFAULT_ENDIAN, eprosima::fastcdr::Cdr::DDS_CDR);
        try
        {
            deser.read_encapsulation();
            payload->encapsulation = deser.endianness() == eprosima::fastcdr::Cdr::BIG_ENDIANNESS ? CDR_BE : CDR_LE;
            deser.deserialize(p->index);
            deser.deserialize(p->message);
        }
        catch (eprosima::fastcdr::exception::Exception&)
        {
            return false;
        }
        return true;
    }

    std::function<uint32_t()> getSerializedSizeProvider(void* data) override
    {
        return [data]() -> uint32_t
               {
                   const HelloWorld* p = static_cast<const HelloWorld*>(data);
                   // encapsulation + index + (aligned) length + chars + NUL
                   return 4 + 4 + 4 + static_cast<uint32_t>(p->message.size()) + 1;
               };
    }

    void* createData() override { return new HelloWorld(); }
    void deleteData(void* data) override { delete static_cast<HelloWorld*>(data); }

    bool getKey(void*, eprosima::fastrtps::rtps::InstanceHandle_t*, bool = false) override
    {
        return false;   // NO_KEY topic
    }
};
