// The ns-3 channel of `erni sim --netns --channel ns3`: one ns-3 process, in real time, carrying
// the frames of every node's namespace through an 802.11a ad-hoc network.
//
// Built by erni.sim.ns3 on first use against Debian's libns3-dev (3.37). Two modes:
//
//   emulate:  erni-ns3-channel emulate --node NAME NETNS X Y [--node ...] [options]
//             For each node, opens a TAP device `mesh0` inside namespace NETNS (setns), gives it
//             the MAC address of the node's wifi device, and attaches it to the node's ns-3 FdNetDevice; frames the kernel sends on the
//             TAP go out on the node's WifiNetDevice, frames the wifi device receives are written
//             into the TAP (source address kept). No ns-3 internet stack: Linux does IP.
//             stdin, one line each:  "pos NAME X Y"   move a node (metres)
//                                    "quit"           stop (so does end of input)
//             stdout: "ready N" once the TAPs exist, then once a second
//                     "lag T NOW_MS MAX_MS LATE PROBES" (T: simulated s; lag of the real-time
//                     simulator behind the wall clock, now and at most; probes later than
//                     --late-ms and probes in all).
//   pure:     erni-ns3-channel pure --distance D --packets N --interval S --size B [options]
//             Two nodes D m apart with ns-3's own internet stack and a UdpClient -> UdpServer
//             flow, in simulated time: prints "pure SENT RECEIVED".
//
// Common options: --range-m R (the transmit power is set so that the base rate's frames reach
// about R m; see TxPowerFor), --seed S --run K (ns-3's random number streams).
//
// The model (ns-3's defaults where they fit): 802.11a (5 GHz OFDM, 20 MHz), AdhocWifiMac, the
// YANS PHY with its default error model, propagation LogDistance (exponent 3, 46.68 dB at 1 m:
// ns-3's default for 5 GHz) followed by Nakagami fading (ns-3's default m = 1.5 below 80 m) drawn
// independently per frame, ConstantSpeed propagation delay, Minstrel rate control for unicast
// frames; broadcast and multicast go at the base rate (6 Mb/s) without retries, as in 802.11.

#include "ns3/core-module.h"
#include "ns3/fd-net-device-module.h"
#include "ns3/internet-module.h"
#include "ns3/applications-module.h"
#include "ns3/mobility-module.h"
#include "ns3/network-module.h"
#include "ns3/wifi-module.h"

#include <atomic>
#include <chrono>
#include <cmath>
#include <cstring>
#include <fcntl.h>
#include <iostream>
#include <linux/if.h>
#include <linux/if_tun.h>
#include <map>
#include <net/if_arp.h>
#include <sched.h>
#include <sstream>
#include <string>
#include <sys/ioctl.h>
#include <thread>
#include <unistd.h>
#include <vector>

using namespace ns3;

namespace
{

// The mean Rx power (dBm) at the range asked for: the minimum RSSI of ns-3's default preamble
// detection (ThresholdPreambleDetectionModel), below which a frame is not received at all. With
// Nakagami fading and the MAC's retries a unicast datagram then gets through about 95 % of the
// time at that range and half the time at 1.2 times it (bench/bench_ns3_channel.py).
constexpr double kEdgeRxDbm = -82.0;
constexpr double kRefLossDb = 46.6777;  // LogDistance's default reference loss at 1 m
constexpr double kExponent = 3.0;       // LogDistance's default exponent

double
TxPowerFor(double rangeM)
{
    return kEdgeRxDbm + kRefLossDb + 10.0 * kExponent * std::log10(rangeM);
}

struct Options
{
    double rangeM = 10.0;
    uint32_t seed = 1;
    uint32_t run = 1;
    double lateMs = 50.0;
};

NetDeviceContainer
InstallWifi(NodeContainer& nodes, const Options& opt)
{
    WifiHelper wifi;
    wifi.SetStandard(WIFI_STANDARD_80211a);
    wifi.SetRemoteStationManager("ns3::MinstrelWifiManager");
    YansWifiChannelHelper channelHelper;
    channelHelper.SetPropagationDelay("ns3::ConstantSpeedPropagationDelayModel");
    channelHelper.AddPropagationLoss("ns3::LogDistancePropagationLossModel",
                                     "Exponent", DoubleValue(kExponent),
                                     "ReferenceLoss", DoubleValue(kRefLossDb));
    channelHelper.AddPropagationLoss("ns3::NakagamiPropagationLossModel");
    Ptr<YansWifiChannel> channel = channelHelper.Create();
    YansWifiPhyHelper phy;
    phy.SetChannel(channel);
    double tx = TxPowerFor(opt.rangeM);
    phy.Set("TxPowerStart", DoubleValue(tx));
    phy.Set("TxPowerEnd", DoubleValue(tx));
    WifiMacHelper mac;
    mac.SetType("ns3::AdhocWifiMac");
    NetDeviceContainer devices = wifi.Install(phy, mac, nodes);
    int64_t stream = 1;
    stream += channelHelper.AssignStreams(channel, stream);
    wifi.AssignStreams(devices, stream);
    MobilityHelper mobility;
    mobility.SetMobilityModel("ns3::ConstantPositionMobilityModel");
    mobility.Install(nodes);
    return devices;
}

[[noreturn]] void
Fail(const std::string& why)
{
    std::cerr << "erni-ns3-channel: " << why << std::endl;
    std::exit(2);
}

// --- emulation -------------------------------------------------------------------------------

struct EmuNode
{
    std::string name;
    std::string netns;
    Mac48Address mac;
    double x = 0, y = 0;
    int fd = -1;
    Ptr<Node> node;
    Ptr<FdNetDevice> tap;
    Ptr<WifiNetDevice> wifi;
};

// frames the MAC gave up on: [0] queue full, [1] too long in the queue, [2] retry limit reached
uint64_t g_dropped[4] = {0, 0, 0, 0};
uint64_t g_sent = 0;  // frames handed from the TAPs to the wifi devices

void
Dropped(WifiMacDropReason reason, Ptr<const WifiMpdu>)
{
    if (reason == WIFI_MAC_DROP_FAILED_ENQUEUE)
        g_dropped[0]++;
    else if (reason == WIFI_MAC_DROP_EXPIRED_LIFETIME || reason == WIFI_MAC_DROP_QOS_OLD_PACKET)
        g_dropped[1]++;
    else if (reason == WIFI_MAC_DROP_REACHED_RETRY_LIMIT)
        g_dropped[2]++;
}

int
OpenTapIn(const std::string& netns, const Mac48Address& mac)
{
    int home = open("/proc/self/ns/net", O_RDONLY | O_CLOEXEC);
    int there = open(("/run/netns/" + netns).c_str(), O_RDONLY | O_CLOEXEC);
    if (home < 0 || there < 0)
        Fail("no network namespace " + netns + ": " + std::strerror(errno));
    if (setns(there, CLONE_NEWNET) != 0)
        Fail("cannot enter namespace " + netns + ": " + std::strerror(errno));
    int fd = open("/dev/net/tun", O_RDWR | O_CLOEXEC);
    if (fd < 0)
        Fail(std::string("cannot open /dev/net/tun: ") + std::strerror(errno));
    struct ifreq ifr;
    std::memset(&ifr, 0, sizeof(ifr));
    ifr.ifr_flags = IFF_TAP | IFF_NO_PI;
    std::strncpy(ifr.ifr_name, "mesh0", IFNAMSIZ - 1);
    if (ioctl(fd, TUNSETIFF, &ifr) != 0)
        Fail("cannot create TAP mesh0 in " + netns + ": " + std::strerror(errno));
    std::memset(&ifr.ifr_hwaddr, 0, sizeof(ifr.ifr_hwaddr));
    ifr.ifr_hwaddr.sa_family = ARPHRD_ETHER;
    mac.CopyTo(reinterpret_cast<uint8_t*>(ifr.ifr_hwaddr.sa_data));
    if (ioctl(fd, SIOCSIFHWADDR, &ifr) != 0)
        Fail("cannot set the MAC address of mesh0 in " + netns + ": " + std::strerror(errno));
    if (setns(home, CLONE_NEWNET) != 0)
        Fail(std::string("cannot return to the launcher's namespace: ") + std::strerror(errno));
    close(there);
    close(home);
    return fd;
}

// kernel -> air: the TAP's frames carry the node's own MAC (the TAP has the wifi device's address)
bool
FromTap(Ptr<WifiNetDevice> wifi, Ptr<NetDevice>, Ptr<const Packet> packet, uint16_t protocol,
        const Address&, const Address& to, NetDevice::PacketType)
{
    g_sent++;
    wifi->Send(packet->Copy(), to, protocol);
    return true;
}

// air -> kernel: what the wifi device hears for this node (or for everyone), source kept
bool
FromAir(Ptr<FdNetDevice> tap, Ptr<NetDevice>, Ptr<const Packet> packet, uint16_t protocol,
        const Address& from, const Address& to, NetDevice::PacketType type)
{
    if (type != NetDevice::PACKET_OTHERHOST)
        tap->SendFrom(packet->Copy(), from, to, protocol);
    return true;
}

struct LagProbe
{
    std::chrono::steady_clock::time_point origin;
    bool started = false;
    double maxMs = 0;
    uint64_t late = 0;
    uint64_t probes = 0;
    double lateMs = 50;
    uint32_t sinceReport = 0;
};

LagProbe g_probe;

void
Probe()
{
    auto now = std::chrono::steady_clock::now();
    if (!g_probe.started)
    {
        g_probe.origin = now - std::chrono::nanoseconds(Simulator::Now().GetNanoSeconds());
        g_probe.started = true;
    }
    double wallMs = std::chrono::duration<double, std::milli>(now - g_probe.origin).count();
    double lagMs = wallMs - Simulator::Now().GetSeconds() * 1000.0;
    g_probe.probes++;
    if (lagMs > g_probe.maxMs)
        g_probe.maxMs = lagMs;
    if (lagMs > g_probe.lateMs)
        g_probe.late++;
    if (++g_probe.sinceReport >= 10)
    {
        g_probe.sinceReport = 0;
        std::printf("lag %.1f %.1f %.1f %llu %llu\n", Simulator::Now().GetSeconds(), lagMs,
                    g_probe.maxMs, (unsigned long long)g_probe.late,
                    (unsigned long long)g_probe.probes);
        std::printf("mac %llu %llu %llu %llu\n", (unsigned long long)g_sent,
                    (unsigned long long)g_dropped[0], (unsigned long long)g_dropped[1],
                    (unsigned long long)g_dropped[2]);
        std::fflush(stdout);
    }
    Simulator::Schedule(MilliSeconds(100), &Probe);
}

void
Move(Ptr<MobilityModel> mobility, double x, double y)
{
    mobility->SetPosition(Vector(x, y, 0.0));
}

void
Stop()
{
    Simulator::Stop();
}

void
ReadCommands(std::map<std::string, EmuNode*> byName)
{
    std::string line;
    while (std::getline(std::cin, line))
    {
        std::istringstream in(line);
        std::string verb;
        in >> verb;
        if (verb == "quit")
            break;
        if (verb == "pos")
        {
            std::string name;
            double x, y;
            if (!(in >> name >> x >> y))
            {
                std::cerr << "erni-ns3-channel: ignored line: " << line << std::endl;
                continue;
            }
            auto it = byName.find(name);
            if (it == byName.end())
            {
                std::cerr << "erni-ns3-channel: no node " << name << std::endl;
                continue;
            }
            Ptr<Node> node = it->second->node;
            Simulator::ScheduleWithContext(node->GetId(), Seconds(0), &Move,
                                           node->GetObject<MobilityModel>(), x, y);
        }
    }
    Simulator::ScheduleWithContext(0xffffffff, Seconds(0), &Stop);
}

int
Emulate(std::vector<EmuNode>& nodes, const Options& opt)
{
    GlobalValue::Bind("SimulatorImplementationType", StringValue("ns3::RealtimeSimulatorImpl"));
    // best effort: a simulator that falls behind runs its events late rather than aborting; the
    // lag probe reports by how much
    Config::SetDefault("ns3::RealtimeSimulatorImpl::SynchronizationMode", StringValue("BestEffort"));
    NodeContainer container;
    container.Create(nodes.size());
    NetDeviceContainer devices = InstallWifi(container, opt);
    std::map<std::string, EmuNode*> byName;
    for (size_t i = 0; i < nodes.size(); ++i)
    {
        EmuNode& n = nodes[i];
        n.node = container.Get(i);
        n.wifi = DynamicCast<WifiNetDevice>(devices.Get(i));
        // the TAP takes the wifi device's address (the MAC acknowledges frames to the address it
        // was made with): the kernel's frames then name the right node, and go out unchanged
        n.mac = Mac48Address::ConvertFrom(n.wifi->GetAddress());
        n.fd = OpenTapIn(n.netns, n.mac);
        n.node->GetObject<MobilityModel>()->SetPosition(Vector(n.x, n.y, 0.0));
        n.tap = CreateObject<FdNetDevice>();
        n.tap->SetAddress(n.mac);
        n.tap->SetFileDescriptor(n.fd);
        n.node->AddDevice(n.tap);
        n.tap->SetPromiscReceiveCallback(MakeBoundCallback(&FromTap, n.wifi));
        n.wifi->SetPromiscReceiveCallback(MakeBoundCallback(&FromAir, n.tap));
        n.wifi->GetMac()->TraceConnectWithoutContext("DroppedMpdu", MakeCallback(&Dropped));
        byName[n.name] = &n;
    }
    g_probe.lateMs = opt.lateMs;
    Simulator::Schedule(Seconds(0), &Probe);
    std::printf("ready %zu\n", nodes.size());
    std::fflush(stdout);
    std::thread reader(ReadCommands, byName);
    reader.detach();
    Simulator::Run();
    std::printf("done %.1f %llu %llu\n", g_probe.maxMs, (unsigned long long)g_probe.late,
                (unsigned long long)g_probe.probes);
    std::fflush(stdout);
    Simulator::Destroy();
    std::_Exit(0);  // the reader thread may still sit in getline
}

// --- the same channel without namespaces -----------------------------------------------------

int
Pure(double distance, uint32_t packets, double interval, uint32_t size, const Options& opt)
{
    NodeContainer nodes;
    nodes.Create(2);
    NetDeviceContainer devices = InstallWifi(nodes, opt);
    nodes.Get(0)->GetObject<MobilityModel>()->SetPosition(Vector(0, 0, 0));
    nodes.Get(1)->GetObject<MobilityModel>()->SetPosition(Vector(distance, 0, 0));
    InternetStackHelper internet;
    internet.Install(nodes);
    Ipv4AddressHelper ipv4;
    ipv4.SetBase("10.1.1.0", "255.255.255.0");
    Ipv4InterfaceContainer ifaces = ipv4.Assign(devices);
    // ns-3's ARP gives up on a neighbour for 100 s after 3 lost requests, Linux's asks again at
    // the next datagram: the neighbours are known from the start, so that only the channel counts
    NeighborCacheHelper neighbors;
    neighbors.PopulateNeighborCache();
    UdpServerHelper server(9);
    ApplicationContainer sink = server.Install(nodes.Get(1));
    sink.Start(Seconds(0.0));
    // as Mesh.udp_flows does: 5 uncounted datagrams 50 ms apart (to a port nobody serves) so that
    // ARP has resolved the receiver, 1 s of quiet, then the counted ones
    UdpClientHelper warm(ifaces.GetAddress(1), 10);
    warm.SetAttribute("MaxPackets", UintegerValue(5));
    warm.SetAttribute("Interval", TimeValue(Seconds(0.05)));
    warm.SetAttribute("PacketSize", UintegerValue(size));
    ApplicationContainer warmApp = warm.Install(nodes.Get(0));
    warmApp.Start(Seconds(1.0));
    UdpClientHelper client(ifaces.GetAddress(1), 9);
    client.SetAttribute("MaxPackets", UintegerValue(packets));
    client.SetAttribute("Interval", TimeValue(Seconds(interval)));
    // UdpClient puts a 12-byte sequence header into each payload: the payload stays `size`
    client.SetAttribute("PacketSize", UintegerValue(size));
    ApplicationContainer app = client.Install(nodes.Get(0));
    app.Start(Seconds(2.25));
    Simulator::Stop(Seconds(2.25 + packets * interval + 2.0));
    Simulator::Run();
    uint64_t got = DynamicCast<UdpServer>(sink.Get(0))->GetReceived();
    std::printf("pure %u %llu\n", packets, (unsigned long long)got);
    Simulator::Destroy();
    return 0;
}

double
Number(const char* s, const char* what)
{
    char* end = nullptr;
    double v = std::strtod(s, &end);
    if (end == s || *end != '\0' || !std::isfinite(v))
        Fail(std::string(what) + ": expected a number, got " + s);
    return v;
}

} // namespace

int
main(int argc, char** argv)
{
    if (argc < 2)
        Fail("usage: erni-ns3-channel emulate|pure [options]");
    std::string mode = argv[1];
    Options opt;
    std::vector<EmuNode> nodes;
    double distance = 0, interval = 0.01;
    uint32_t packets = 100, size = 500;
    for (int i = 2; i < argc; ++i)
    {
        std::string a = argv[i];
        auto need = [&](int k) {
            if (i + k >= argc)
                Fail(a + " needs " + std::to_string(k) + " value(s)");
        };
        if (a == "--node")
        {
            need(4);
            EmuNode n;
            n.name = argv[i + 1];
            n.netns = argv[i + 2];
            n.x = Number(argv[i + 3], "x");
            n.y = Number(argv[i + 4], "y");
            nodes.push_back(n);
            i += 4;
        }
        else if (a == "--range-m" || a == "--seed" || a == "--run" || a == "--late-ms" ||
                 a == "--distance" || a == "--packets" || a == "--interval" || a == "--size")
        {
            need(1);
            double v = Number(argv[++i], a.c_str());
            if (a == "--range-m")
                opt.rangeM = v;
            else if (a == "--seed")
                opt.seed = static_cast<uint32_t>(v);
            else if (a == "--run")
                opt.run = static_cast<uint32_t>(v);
            else if (a == "--late-ms")
                opt.lateMs = v;
            else if (a == "--distance")
                distance = v;
            else if (a == "--packets")
                packets = static_cast<uint32_t>(v);
            else if (a == "--interval")
                interval = v;
            else
                size = static_cast<uint32_t>(v);
        }
        else
            Fail("unknown option " + a);
    }
    if (!(opt.rangeM > 1.0))
        Fail("--range-m must be more than 1 m");
    RngSeedManager::SetSeed(opt.seed ? opt.seed : 1);
    RngSeedManager::SetRun(opt.run);
    if (mode == "emulate")
    {
        if (nodes.empty())
            Fail("emulate needs at least one --node");
        return Emulate(nodes, opt);
    }
    if (mode == "pure")
        return Pure(distance, packets, interval, size, opt);
    Fail("unknown mode " + mode);
}
