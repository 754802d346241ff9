// A small ROS 2 Mecanum robot on Fast DDS (eProsima's C++ API), independent of mecanum-hil.
//
// Written from the ROS 2 conventions alone: a ROS 2 message pkg/msg/Type is the DDS type
// pkg::msg::dds_::Type_ (a final struct of the message's fields in order, plain CDR with the
// 4-byte encapsulation header), a ROS topic /name is the DDS topic rt/name, ROS_DOMAIN_ID is
// the DDS domain. The message types are hand-written TopicDataType classes over Fast CDR, as
// rmw_fastrtps' type support lays them out; nothing is generated.
//
// The robot: geometry_msgs/Twist on rt/cmd_vel (reliable reader, ROS 2's default QoS) gives
// the four Mecanum wheel targets (the project's pinned kinematics, docs/conventions.md, with
// the paper robot's r = 0.102 m and lx + ly = 0.465 m); each wheel runs the model
// W/R = (A s + C) / (s^2 + (A + B) s + C), A = 14.7, B = 16.1, C = 303 (a PI loop around a
// first-order motor), integrated exactly (zero-order hold) on a 1 ms step; without a twist for
// 0.5 s the targets are zero. sensor_msgs/JointState (rad/s) on rt/joint_states and
// nav_msgs/Odometry on rt/odom at 50 Hz, stamped with the wall clock.
//
// DDS stays on this machine: the builtin transports are off, one UDPv4 transport is limited
// to 127.0.0.1, and discovery is unicast to the RTPS well-known ports of 127.0.0.1.
//
// Usage: robot [--domain N] [--best-effort] [--log FILE]
//   --best-effort  publish joint states and odometry best effort (ROS's sensor-data QoS)
//   --log FILE     one line per twist received: linear x y z, angular x y z
// Prints "ready" once its endpoints exist; ends on SIGTERM or SIGINT.

#include <fastcdr/Cdr.h>
#include <fastcdr/FastBuffer.h>
#include <fastdds/dds/domain/DomainParticipant.hpp>
#include <fastdds/dds/domain/DomainParticipantFactory.hpp>
#include <fastdds/dds/publisher/DataWriter.hpp>
#include <fastdds/dds/publisher/Publisher.hpp>
#include <fastdds/dds/subscriber/DataReader.hpp>
#include <fastdds/dds/subscriber/DataReaderListener.hpp>
#include <fastdds/dds/subscriber/SampleInfo.hpp>
#include <fastdds/dds/subscriber/Subscriber.hpp>
#include <fastdds/dds/topic/TopicDataType.hpp>
#include <fastdds/dds/topic/TypeSupport.hpp>
#include <fastdds/rtps/transport/UDPv4TransportDescriptor.h>
#include <fastrtps/utils/IPLocator.h>

#include <array>
#include <atomic>
#include <chrono>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <functional>
#include <iostream>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

using namespace eprosima::fastdds::dds;
using eprosima::fastcdr::Cdr;
using eprosima::fastcdr::FastBuffer;
using eprosima::fastrtps::rtps::InstanceHandle_t;
using eprosima::fastrtps::rtps::SerializedPayload_t;

// -- messages -------------------------------------------------------------------------------

struct Time { int32_t sec = 0; uint32_t nanosec = 0; };
struct Header { Time stamp; std::string frame_id; };
struct Vector3 { double x = 0, y = 0, z = 0; };
struct Twist { Vector3 linear, angular; };
struct JointState {
    Header header;
    std::vector<std::string> name;
    std::vector<double> position, velocity, effort;
};
struct Odometry {
    Header header;
    std::string child_frame_id;
    double position[3] = {0, 0, 0};
    double orientation[4] = {0, 0, 0, 1};  // x y z w
    double pose_covariance[36] = {};
    Twist twist;
    double twist_covariance[36] = {};
};

static void put(Cdr& c, const Header& h) { c << h.stamp.sec << h.stamp.nanosec << h.frame_id; }
static void get(Cdr& c, Header& h) { c >> h.stamp.sec >> h.stamp.nanosec >> h.frame_id; }
static void put(Cdr& c, const Vector3& v) { c << v.x << v.y << v.z; }
static void get(Cdr& c, Vector3& v) { c >> v.x >> v.y >> v.z; }
static void put(Cdr& c, const Twist& t) { put(c, t.linear); put(c, t.angular); }
static void get(Cdr& c, Twist& t) { get(c, t.linear); get(c, t.angular); }
static void put(Cdr& c, const JointState& j) {
    put(c, j.header);
    c << j.name << j.position << j.velocity << j.effort;
}
static void get(Cdr& c, JointState& j) {
    get(c, j.header);
    c >> j.name >> j.position >> j.velocity >> j.effort;
}
static void put(Cdr& c, const Odometry& o) {
    put(c, o.header);
    c << o.child_frame_id;
    c.serializeArray(o.position, 3);
    c.serializeArray(o.orientation, 4);
    c.serializeArray(o.pose_covariance, 36);
    put(c, o.twist);
    c.serializeArray(o.twist_covariance, 36);
}
static void get(Cdr& c, Odometry& o) {
    get(c, o.header);
    c >> o.child_frame_id;
    c.deserializeArray(o.position, 3);
    c.deserializeArray(o.orientation, 4);
    c.deserializeArray(o.pose_covariance, 36);
    get(c, o.twist);
    c.deserializeArray(o.twist_covariance, 36);
}

// Upper bounds of the serialised sizes (encapsulation, alignment padding included).
static uint32_t bound(const std::string& s) { return 4 + s.size() + 1 + 7; }
static uint32_t bound(const Header& h) { return 8 + bound(h.frame_id); }
static uint32_t bound(const Twist&) { return 48 + 8; }
static uint32_t bound(const JointState& j) {
    uint32_t n = 4 + bound(j.header) + 8;
    for (const auto& s : j.name) n += bound(s);
    n += 3 * 16 + 8 * (j.position.size() + j.velocity.size() + j.effort.size());
    return n;
}
static uint32_t bound(const Odometry& o) {
    return 4 + bound(o.header) + bound(o.child_frame_id) + 8 * (3 + 4 + 36 + 6 + 36) + 16;
}

// The encapsulation identifier of the last payload deserialised (0x0001: CDR little endian).
static std::atomic<int> g_last_encapsulation{-1};

// A final ROS 2 message type in plain CDR, no key.
template <typename T>
class RosType : public TopicDataType {
public:
    RosType(const char* dds_name, uint32_t typical_size) {
        setName(dds_name);
        m_typeSize = typical_size;
        m_isGetKeyDefined = false;
    }
    bool serialize(void* data, SerializedPayload_t* payload) override {
        const T* msg = static_cast<const T*>(data);
        FastBuffer buffer(reinterpret_cast<char*>(payload->data), payload->max_size);
        Cdr ser(buffer, Cdr::DEFAULT_ENDIAN, Cdr::DDS_CDR);
        payload->encapsulation = ser.endianness() == Cdr::BIG_ENDIANNESS ? CDR_BE : CDR_LE;
        try {
            ser.serialize_encapsulation();
            put(ser, *msg);
        } catch (const std::exception&) {
            return false;
        }
        payload->length = static_cast<uint32_t>(ser.getSerializedDataLength());
        return true;
    }
    bool deserialize(SerializedPayload_t* payload, void* data) override {
        T* msg = static_cast<T*>(data);
        FastBuffer buffer(reinterpret_cast<char*>(payload->data), payload->length);
        Cdr des(buffer, Cdr::DEFAULT_ENDIAN, Cdr::DDS_CDR);
        try {
            des.read_encapsulation();
            payload->encapsulation = des.endianness() == Cdr::BIG_ENDIANNESS ? CDR_BE : CDR_LE;
            if (payload->length >= 2) {
                g_last_encapsulation = (payload->data[0] << 8) | payload->data[1];
            }
            get(des, *msg);
        } catch (const std::exception&) {
            return false;
        }
        return true;
    }
    std::function<uint32_t()> getSerializedSizeProvider(void* data) override {
        return [data]() { return bound(*static_cast<T*>(data)); };
    }
    void* createData() override { return new T(); }
    void deleteData(void* data) override { delete static_cast<T*>(data); }
    bool getKey(void*, InstanceHandle_t*, bool) override { return false; }
};

// -- the robot ------------------------------------------------------------------------------

namespace robot {
constexpr double kPi = 3.14159265358979323846;
constexpr double kRadius = 0.102;       // wheel radius r [m] (drivers/tdam-stm.toml)
constexpr double kLxPlusLy = 0.465;     // lx + ly [m]
constexpr double kK = kLxPlusLy / kRadius;
constexpr double kA = 14.7, kB = 16.1, kC = 303.0;
constexpr double kStep = 0.001;          // model step [s]
constexpr int kPublishEvery = 20;        // steps between joint states: 50 Hz
constexpr double kCommandTimeout = 0.5;  // [s]
constexpr double kMpsPerRpm = 2.0 * kPi * kRadius / 60.0;
constexpr double kRadSPerRpm = 2.0 * kPi / 60.0;
const char* const kJoints[4] = {"front_left_wheel_joint", "front_right_wheel_joint",
                                "rear_left_wheel_joint", "rear_right_wheel_joint"};
}  // namespace robot

// Wheel targets [rpm] of a twist (m/s, rad/s): the pinned inverse kinematics,
// w1 = vx - vy - k wz, w2 = vx + vy + k wz, w3 = vx + vy - k wz, w4 = vx - vy + k wz, with the
// body velocity and turning speed in wheel-rpm units.
static std::array<double, 4> wheel_targets(const Twist& t) {
    using namespace robot;
    const double vx = t.linear.x / kMpsPerRpm, vy = t.linear.y / kMpsPerRpm;
    const double wz = t.angular.z / kRadSPerRpm;  // body turns per minute
    return {vx - vy - kK * wz, vx + vy + kK * wz, vx + vy - kK * wz, vx - vy + kK * wz};
}

// One wheel, x = (w [rpm], z = integral of (r - w)):
//   w' = -(A + B) w + C z + A r,  z' = r - w   ->   W/R = (A s + C) / (s^2 + (A + B) s + C).
// Discretised with a zero-order hold on r: x+ = Phi x + Gamma r (series of exp(M h)).
struct WheelModel {
    double phi[2][2], gamma[2];
    WheelModel() {
        using namespace robot;
        const double m[2][2] = {{-(kA + kB), kC}, {-1.0, 0.0}};
        const double b[2] = {kA, 1.0};
        double term[2][2] = {{1, 0}, {0, 1}};  // (M h)^n / n!
        double p[2][2] = {{0, 0}, {0, 0}}, q[2][2] = {{0, 0}, {0, 0}};  // Phi, Gamma / B
        for (int n = 0; n < 30; ++n) {
            for (int i = 0; i < 2; ++i)
                for (int j = 0; j < 2; ++j) {
                    p[i][j] += term[i][j];
                    q[i][j] += term[i][j] * kStep / (n + 1);  // M^n h^(n+1) / (n+1)!
                }
            double next[2][2];
            for (int i = 0; i < 2; ++i)
                for (int j = 0; j < 2; ++j)
                    next[i][j] = (m[i][0] * term[0][j] + m[i][1] * term[1][j]) * kStep / (n + 1);
            std::memcpy(term, next, sizeof term);
        }
        std::memcpy(phi, p, sizeof p);
        for (int i = 0; i < 2; ++i) gamma[i] = q[i][0] * b[0] + q[i][1] * b[1];
    }
};

static volatile std::sig_atomic_t g_stop = 0;
static void on_signal(int) { g_stop = 1; }

class CommandListener : public DataReaderListener {
public:
    explicit CommandListener(std::ofstream* log) : log_(log) {}
    void on_data_available(DataReader* reader) override {
        Twist twist;
        SampleInfo info;
        while (reader->take_next_sample(&twist, &info) == ReturnCode_t::RETCODE_OK) {
            if (!info.valid_data) continue;
            std::lock_guard<std::mutex> lock(mutex);
            targets = wheel_targets(twist);
            last = std::chrono::steady_clock::now();
            have_command = true;
            ++received;
            if (log_ && log_->is_open()) {
                char line[256];
                std::snprintf(line, sizeof line, "%.17g %.17g %.17g %.17g %.17g %.17g\n",
                              twist.linear.x, twist.linear.y, twist.linear.z, twist.angular.x,
                              twist.angular.y, twist.angular.z);
                *log_ << line << std::flush;
            }
        }
    }
    void on_subscription_matched(DataReader*, const SubscriptionMatchedStatus& s) override {
        std::fprintf(stderr, "cmd_vel: %d publisher(s) matched\n", s.current_count);
    }
    void on_requested_incompatible_qos(DataReader*,
                                       const RequestedIncompatibleQosStatus& s) override {
        std::fprintf(stderr, "cmd_vel: incompatible QoS offered (last policy id %u)\n",
                     static_cast<unsigned>(s.last_policy_id));
    }
    std::mutex mutex;
    std::array<double, 4> targets{};
    std::chrono::steady_clock::time_point last;
    bool have_command = false;
    long received = 0;

private:
    std::ofstream* log_;
};

static long long wall_ns() {
    return std::chrono::duration_cast<std::chrono::nanoseconds>(
        std::chrono::system_clock::now().time_since_epoch()).count();
}

// A header stamp (builtin_interfaces/Time) of a wall-clock time [ns since the epoch].
static Time stamp_at(long long ns) {
    Time t;
    t.sec = static_cast<int32_t>(ns / 1000000000LL);
    t.nanosec = static_cast<uint32_t>(ns % 1000000000LL);
    return t;
}

static int usage() {
    std::fprintf(stderr, "usage: robot [--domain N] [--best-effort] [--log FILE]\n");
    return 2;
}

int main(int argc, char** argv) {
    int domain = 0;
    bool best_effort = false;
    std::string log_path;
    for (int i = 1; i < argc; ++i) {
        const std::string a = argv[i];
        if (a == "--domain" && i + 1 < argc) domain = std::atoi(argv[++i]);
        else if (a == "--best-effort") best_effort = true;
        else if (a == "--log" && i + 1 < argc) log_path = argv[++i];
        else return usage();
    }
    std::signal(SIGTERM, on_signal);
    std::signal(SIGINT, on_signal);
    std::ofstream log;
    if (!log_path.empty()) {
        log.open(log_path);
        if (!log) {
            std::fprintf(stderr, "cannot write %s\n", log_path.c_str());
            return 2;
        }
    }

    // The loopback only: one UDPv4 transport on 127.0.0.1, discovery by unicast. An initial
    // peer without a port stands for the metatraffic unicast ports of participant ids
    // 0 .. maxInitialPeersRange - 1 (PB + DG domain + d1 + PG id = 7410 + 250 domain + 2 id),
    // which covers Cyclone's automatic participant indices 0..60.
    DomainParticipantQos pqos;
    pqos.name("fastdds_mecanum_robot");
    pqos.transport().use_builtin_transports = false;
    auto udp = std::make_shared<eprosima::fastdds::rtps::UDPv4TransportDescriptor>();
    udp->interfaceWhiteList.push_back("127.0.0.1");
    udp->maxInitialPeersRange = 61;
    pqos.transport().user_transports.push_back(udp);
    eprosima::fastrtps::rtps::Locator_t loopback;
    loopback.kind = LOCATOR_KIND_UDPv4;
    eprosima::fastrtps::rtps::IPLocator::setIPv4(loopback, 127, 0, 0, 1);
    loopback.port = 0;  // filled in: the well-known ports
    auto& wire = pqos.wire_protocol();
    wire.builtin.initialPeersList.push_back(loopback);
    wire.builtin.metatrafficUnicastLocatorList.push_back(loopback);
    wire.default_unicast_locator_list.push_back(loopback);

    auto* factory = DomainParticipantFactory::get_instance();
    DomainParticipant* participant = factory->create_participant(domain, pqos);
    if (!participant) {
        std::fprintf(stderr, "cannot create a participant in domain %d\n", domain);
        return 1;
    }
    TypeSupport twist_type(new RosType<Twist>("geometry_msgs::msg::dds_::Twist_", 4 + 48));
    TypeSupport joint_type(
        new RosType<JointState>("sensor_msgs::msg::dds_::JointState_", 1024));
    TypeSupport odom_type(new RosType<Odometry>("nav_msgs::msg::dds_::Odometry_", 1024));
    twist_type.register_type(participant);
    joint_type.register_type(participant);
    odom_type.register_type(participant);
    Topic* cmd_topic = participant->create_topic("rt/cmd_vel", twist_type.get_type_name(),
                                                 TOPIC_QOS_DEFAULT);
    Topic* joint_topic = participant->create_topic(
        "rt/joint_states", joint_type.get_type_name(), TOPIC_QOS_DEFAULT);
    Topic* odom_topic = participant->create_topic("rt/odom", odom_type.get_type_name(),
                                                  TOPIC_QOS_DEFAULT);
    Publisher* publisher = participant->create_publisher(PUBLISHER_QOS_DEFAULT);
    Subscriber* subscriber = participant->create_subscriber(SUBSCRIBER_QOS_DEFAULT);
    if (!cmd_topic || !joint_topic || !odom_topic || !publisher || !subscriber) {
        std::fprintf(stderr, "cannot create the topics\n");
        return 1;
    }

    // ROS 2's default profile: reliable, volatile, keep last 10 (sensor data: best effort).
    DataReaderQos rqos = DATAREADER_QOS_DEFAULT;
    rqos.reliability().kind = RELIABLE_RELIABILITY_QOS;
    rqos.durability().kind = VOLATILE_DURABILITY_QOS;
    rqos.history().kind = KEEP_LAST_HISTORY_QOS;
    rqos.history().depth = 10;
    rqos.data_sharing().off();
    DataWriterQos wqos = DATAWRITER_QOS_DEFAULT;
    wqos.reliability().kind = best_effort ? BEST_EFFORT_RELIABILITY_QOS
                                          : RELIABLE_RELIABILITY_QOS;
    wqos.durability().kind = VOLATILE_DURABILITY_QOS;
    wqos.history().kind = KEEP_LAST_HISTORY_QOS;
    wqos.history().depth = 10;
    wqos.data_sharing().off();

    CommandListener listener(log_path.empty() ? nullptr : &log);
    DataReader* cmd_reader = subscriber->create_datareader(cmd_topic, rqos, &listener);
    DataWriter* joint_writer = publisher->create_datawriter(joint_topic, wqos);
    DataWriter* odom_writer = publisher->create_datawriter(odom_topic, wqos);
    if (!cmd_reader || !joint_writer || !odom_writer) {
        std::fprintf(stderr, "cannot create the readers and writers\n");
        return 1;
    }
    std::printf("ready\n");
    std::fflush(stdout);

    using namespace robot;
    const WheelModel model;
    double w[4] = {0, 0, 0, 0}, z[4] = {0, 0, 0, 0}, angle[4] = {0, 0, 0, 0};
    double px = 0, py = 0, yaw = 0;
    JointState js;
    for (const char* j : kJoints) js.name.emplace_back(j);
    js.position.assign(4, 0.0);
    js.velocity.assign(4, 0.0);
    Odometry od;
    od.header.frame_id = "odom";
    od.child_frame_id = "base_link";
    int first_encapsulation_reported = -1;

    const auto step = std::chrono::microseconds(static_cast<int>(kStep * 1e6));
    const long long step_ns = static_cast<long long>(kStep * 1e9);
    auto next = std::chrono::steady_clock::now();
    const long long start_ns = wall_ns();
    long tick = 0;
    while (!g_stop) {
        std::array<double, 4> r{};
        {
            std::lock_guard<std::mutex> lock(listener.mutex);
            const auto now = std::chrono::steady_clock::now();
            if (listener.have_command &&
                std::chrono::duration<double>(now - listener.last).count() < kCommandTimeout) {
                r = listener.targets;
            }
        }
        for (int i = 0; i < 4; ++i) {
            const double wn = model.phi[0][0] * w[i] + model.phi[0][1] * z[i] + model.gamma[0] * r[i];
            const double zn = model.phi[1][0] * w[i] + model.phi[1][1] * z[i] + model.gamma[1] * r[i];
            angle[i] += 0.5 * (w[i] + wn) * kRadSPerRpm * kStep;
            w[i] = wn;
            z[i] = zn;
        }
        // odometry from the wheels: the pseudo-inverse of the kinematics
        const double vx = (w[0] + w[1] + w[2] + w[3]) / 4.0 * kMpsPerRpm;
        const double vy = (-w[0] + w[1] + w[2] - w[3]) / 4.0 * kMpsPerRpm;
        const double wz = (-w[0] + w[1] - w[2] + w[3]) / (4.0 * kK) * kRadSPerRpm;
        px += (vx * std::cos(yaw) - vy * std::sin(yaw)) * kStep;
        py += (vx * std::sin(yaw) + vy * std::cos(yaw)) * kStep;
        yaw += wz * kStep;
        if (++tick % kPublishEvery == 0) {
            const Time stamp = stamp_at(start_ns + tick * step_ns);
            js.header.stamp = stamp;
            for (int i = 0; i < 4; ++i) {
                js.position[i] = angle[i];
                js.velocity[i] = w[i] * kRadSPerRpm;
            }
            joint_writer->write(&js);
            od.header.stamp = stamp;
            od.position[0] = px;
            od.position[1] = py;
            od.orientation[2] = std::sin(yaw / 2);
            od.orientation[3] = std::cos(yaw / 2);
            od.twist.linear.x = vx;
            od.twist.linear.y = vy;
            od.twist.angular.z = wz;
            odom_writer->write(&od);
            const int enc = g_last_encapsulation.load();
            if (enc != first_encapsulation_reported && enc >= 0) {
                std::fprintf(stderr, "cmd_vel: encapsulation 0x%04x\n", enc);
                first_encapsulation_reported = enc;
            }
        }
        // real time: the model's clock is the wall clock (after a stall it catches up)
        next += step;
        std::this_thread::sleep_until(next);
    }

    long received;
    {
        std::lock_guard<std::mutex> lock(listener.mutex);
        received = listener.received;
    }
    participant->delete_contained_entities();
    factory->delete_participant(participant);
    if (log.is_open()) log.close();
    std::fprintf(stderr, "stopped: %ld twists received\n", received);
    return 0;
}
