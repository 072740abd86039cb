// A ROS 2-style LaserScan subscriber on plain Fast DDS (no ROS): two readers on one topic, one
// RELIABLE and one BEST_EFFORT (both VOLATILE, KEEP_LAST 10), as rmw_fastrtps makes them for the
// default and the sensor-data QoS profiles. UDPv4 on 127.0.0.1 only, no shared memory.
//
// usage: subscriber DOMAIN TOPIC COUNT TIMEOUT_S
// Prints {"event":"ready"} once both readers exist, then one JSON line per sample received:
// {"reader":"reliable"|"best_effort","sec":..,"nanosec":..,"frame_id":"..","angle_min":..,
//  "angle_max":..,"angle_increment":..,"range_min":..,"range_max":..,"ranges":"<hex>"}
// where "ranges" is the float32 array's little-endian bytes in hex (NaN and infinities exact).
// Exits 0 once each reader has COUNT samples, 2 after TIMEOUT_S seconds without them.
#include "LaserScan.h"
#include "LaserScanPubSubTypes.h"

#include <fastdds/dds/domain/DomainParticipant.hpp>
#include <fastdds/dds/domain/DomainParticipantFactory.hpp>
#include <fastdds/dds/subscriber/DataReader.hpp>
#include <fastdds/dds/subscriber/SampleInfo.hpp>
#include <fastdds/dds/subscriber/Subscriber.hpp>
#include <fastdds/dds/subscriber/qos/DataReaderQos.hpp>
#include <fastdds/dds/topic/TypeSupport.hpp>
#include <fastdds/rtps/transport/UDPv4TransportDescriptor.h>
#include <fastrtps/utils/IPLocator.h>

#include <chrono>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <string>

using namespace eprosima::fastdds::dds;
using eprosima::fastdds::rtps::UDPv4TransportDescriptor;
using eprosima::fastrtps::rtps::IPLocator;
using eprosima::fastrtps::rtps::Locator_t;

static std::string hex_floats(const std::vector<float>& values)
{
    static const char digits[] = "0123456789abcdef";
    std::string out;
    out.reserve(values.size() * 8);
    for (float v : values) {
        unsigned char bytes[4];
        std::memcpy(bytes, &v, 4);  // x86_64 and arm64: little-endian, as the test expects
        for (unsigned char b : bytes) {
            out.push_back(digits[b >> 4]);
            out.push_back(digits[b & 15]);
        }
    }
    return out;
}

static void print_sample(const char* reader, const sensor_msgs::msg::dds_::LaserScan_& s)
{
    const auto& h = s.header();
    std::printf(
        "{\"reader\":\"%s\",\"sec\":%d,\"nanosec\":%u,\"frame_id\":\"%s\",\"angle_min\":%.9g,"
        "\"angle_max\":%.9g,\"angle_increment\":%.9g,\"range_min\":%.9g,\"range_max\":%.9g,"
        "\"ranges\":\"%s\"}\n",
        reader, h.stamp().sec(), h.stamp().nanosec(), h.frame_id().c_str(), s.angle_min(),
        s.angle_max(), s.angle_increment(), s.range_min(), s.range_max(),
        hex_floats(s.ranges()).c_str());
    std::fflush(stdout);
}

int main(int argc, char** argv)
{
    if (argc != 5) {
        std::fprintf(stderr, "usage: %s DOMAIN TOPIC COUNT TIMEOUT_S\n", argv[0]);
        return 1;
    }
    const int domain = std::atoi(argv[1]);
    const std::string topic_name = argv[2];
    const int count = std::atoi(argv[3]);
    const double timeout_s = std::atof(argv[4]);

    DomainParticipantQos pqos;
    pqos.name("depthnav_test_fastdds_subscriber");
    pqos.transport().use_builtin_transports = false;  // no shared memory, no default interfaces
    auto udp = std::make_shared<UDPv4TransportDescriptor>();
    udp->interfaceWhiteList.push_back("127.0.0.1");
    pqos.transport().user_transports.push_back(udp);
    Locator_t peer;  // unicast discovery on loopback (lo has no multicast)
    IPLocator::setIPv4(peer, 127, 0, 0, 1);
    pqos.wire_protocol().builtin.initialPeersList.push_back(peer);

    DomainParticipant* participant =
        DomainParticipantFactory::get_instance()->create_participant(domain, pqos);
    if (participant == nullptr) {
        std::fprintf(stderr, "cannot create a participant on domain %d\n", domain);
        return 1;
    }
    TypeSupport type(new sensor_msgs::msg::dds_::LaserScan_PubSubType());
    type.register_type(participant);
    Topic* topic = participant->create_topic(topic_name, type.get_type_name(), TOPIC_QOS_DEFAULT);
    Subscriber* subscriber = participant->create_subscriber(SUBSCRIBER_QOS_DEFAULT);
    if (topic == nullptr || subscriber == nullptr) {
        std::fprintf(stderr, "cannot create the topic %s\n", topic_name.c_str());
        return 1;
    }
    struct Reader {
        const char* name;
        DataReader* reader;
        int received;
    } readers[2] = {{"reliable", nullptr, 0}, {"best_effort", nullptr, 0}};
    for (Reader& r : readers) {
        DataReaderQos rqos = DATAREADER_QOS_DEFAULT;
        rqos.reliability().kind = std::strcmp(r.name, "reliable") == 0
                                      ? RELIABLE_RELIABILITY_QOS
                                      : BEST_EFFORT_RELIABILITY_QOS;
        rqos.durability().kind = VOLATILE_DURABILITY_QOS;
        rqos.history().kind = KEEP_LAST_HISTORY_QOS;
        rqos.history().depth = 10;
        r.reader = subscriber->create_datareader(topic, rqos);
        if (r.reader == nullptr) {
            std::fprintf(stderr, "cannot create the %s reader\n", r.name);
            return 1;
        }
    }
    std::printf("{\"event\":\"ready\"}\n");
    std::fflush(stdout);

    const auto deadline = std::chrono::steady_clock::now() +
                          std::chrono::milliseconds(static_cast<long long>(timeout_s * 1000));
    sensor_msgs::msg::dds_::LaserScan_ sample;
    SampleInfo info;
    while (readers[0].received < count || readers[1].received < count) {
        if (std::chrono::steady_clock::now() > deadline) {
            std::fprintf(stderr, "timeout: %d reliable and %d best-effort samples of %d\n",
                         readers[0].received, readers[1].received, count);
            return 2;
        }
        for (Reader& r : readers) {
            r.reader->wait_for_unread_message(eprosima::fastrtps::Duration_t(0, 50000000));
            while (r.reader->take_next_sample(&sample, &info) == ReturnCode_t::RETCODE_OK) {
                if (info.valid_data && r.received < count) {
                    print_sample(r.name, sample);
                    ++r.received;
                }
            }
        }
    }
    participant->delete_contained_entities();
    DomainParticipantFactory::get_instance()->delete_participant(participant);
    return 0;
}
