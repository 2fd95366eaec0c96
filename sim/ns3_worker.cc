#include <algorithm>
#include <array>
#include <map>
#include <string>
#include <vector>

namespace tupa_ns3
{
using namespace ns3;

enum Field
{
    TX = 0, RX, DELAY_SUM, DROP_QDISC, DROP_ENQ, DROP_EXPIRED, DROP_RETRY, DROP_OLD, DROP_MACTX,
    DROP_ARP, DROP_TC, BACKLOG_QDISC, BACKLOG_MAC, PPDUS, MPDUS, MCS_SUM, NACKED, RESP_TIMEOUT,
    AP_RX_DROPS, APP_TX, ACKED, AMPDU_MAX, EXPIRED_UNSENT, EXPIRED_TX_SUM, OLD_TX_SUM,
    TX_PER_MPDU_SUM, BACKOFF_DRAWS, BACKOFF_SLOTS, BACKOFF_LONG, MAX_TX_GAP, AP_RX_DBM_SUM,
    AP_RX_MPDUS, DROP_IP, PHY_DROP_BASE
};
static const int N_PHY_REASONS = 25;
static const int NF = PHY_DROP_BASE + N_PHY_REASONS;

struct State
{
    std::vector<std::array<double, NF>> cum;
    std::vector<double> out;  // snapshots: [time, users x NF] appended
    std::vector<double> assocTime;
    std::map<Mac48Address, uint32_t> macToUser;
    std::map<Ipv4Address, uint32_t> ipToUser;
    std::vector<double> lastTx;  // start of each STA's last data PPDU (s), -1: none yet
    std::vector<uint32_t> cw;  // current contention window of each STA's BE Txop
    std::vector<std::map<uint16_t, uint32_t>> txCount;  // per user: sequence number -> sends
    NetDeviceContainer staDevs;
    NodeContainer stas;
    Ptr<FlowMonitor> monitor;
    Ptr<Ipv4FlowClassifier> classifier;
};

static State* g = nullptr;

static uint32_t TakeTxCount(uint32_t u, Ptr<const WifiMpdu> mpdu)
{
    auto& m = g->txCount[u];
    auto it = m.find(mpdu->GetHeader().GetSequenceNumber());
    if (it == m.end()) { return 0; }
    uint32_t n = it->second;
    m.erase(it);
    return n;
}

static void OnDropped(uint32_t u, WifiMacDropReason r, Ptr<const WifiMpdu> mpdu)
{
    if (!mpdu->GetHeader().IsQosData()) { return; }
    g->cum[u][DROP_ENQ + static_cast<int>(r)] += 1;
    uint32_t sent = TakeTxCount(u, mpdu);
    if (r == WIFI_MAC_DROP_EXPIRED_LIFETIME)
    {
        g->cum[u][EXPIRED_TX_SUM] += sent;
        if (sent == 0) { g->cum[u][EXPIRED_UNSENT] += 1; }
    }
    else if (r == WIFI_MAC_DROP_QOS_OLD_PACKET)
    {
        g->cum[u][OLD_TX_SUM] += sent;
    }
}

static void OnMacTxDrop(uint32_t u, Ptr<const Packet>) { g->cum[u][DROP_MACTX] += 1; }
static void OnQdiscDrop(uint32_t u, Ptr<const QueueDiscItem>) { g->cum[u][DROP_QDISC] += 1; }
static void OnArpDrop(uint32_t u, Ptr<const Packet>) { g->cum[u][DROP_ARP] += 1; }
static void OnTcDrop(uint32_t u, Ptr<const Packet>) { g->cum[u][DROP_TC] += 1; }
static void OnAppTx(uint32_t u, Ptr<const Packet>) { g->cum[u][APP_TX] += 1; }

static void OnIpDrop(uint32_t u, const Ipv4Header&, Ptr<const Packet>,
                     Ipv4L3Protocol::DropReason, Ptr<Ipv4>, uint32_t)
{
    g->cum[u][DROP_IP] += 1;
}

static void OnNacked(uint32_t u, Ptr<const WifiMpdu> mpdu)
{
    if (mpdu->GetHeader().IsQosData()) { g->cum[u][NACKED] += 1; }
}

static void OnAcked(uint32_t u, Ptr<const WifiMpdu> mpdu)
{
    if (!mpdu->GetHeader().IsQosData()) { return; }
    g->cum[u][ACKED] += 1;
    g->cum[u][TX_PER_MPDU_SUM] += TakeTxCount(u, mpdu);
}

static void OnMpduTimeout(uint32_t u, uint8_t, Ptr<const WifiMpdu>, const WifiTxVector&)
{
    g->cum[u][RESP_TIMEOUT] += 1;
}

static void OnPsduTimeout(uint32_t u, uint8_t, Ptr<const WifiPsdu>, const WifiTxVector&)
{
    g->cum[u][RESP_TIMEOUT] += 1;
}

static void OnPsduTx(uint32_t u, WifiConstPsduMap psduMap, WifiTxVector txVector, double)
{
    for (const auto& [staId, psdu] : psduMap)
    {
        if (psdu->GetNMpdus() == 0 || !psdu->GetHeader(0).IsQosData()) { continue; }
        double n = static_cast<double>(psdu->GetNMpdus());
        double now = Simulator::Now().GetSeconds();
        if (g->lastTx[u] >= 0 && now - g->lastTx[u] > g->cum[u][MAX_TX_GAP])
        {
            g->cum[u][MAX_TX_GAP] = now - g->lastTx[u];
        }
        g->lastTx[u] = now;
        g->cum[u][PPDUS] += 1;
        g->cum[u][MPDUS] += n;
        g->cum[u][MCS_SUM] += n * txVector.GetMode().GetMcsValue();
        if (n > g->cum[u][AMPDU_MAX]) { g->cum[u][AMPDU_MAX] = n; }
        for (const auto& mpdu : *psdu)
        {
            g->txCount[u][mpdu->GetHeader().GetSequenceNumber()] += 1;
        }
    }
}

static void OnCw(uint32_t u, uint32_t cw, uint8_t) { g->cw[u] = cw; }

static void OnBackoff(uint32_t u, uint32_t slots, uint8_t)
{
    g->cum[u][BACKOFF_DRAWS] += 1;
    g->cum[u][BACKOFF_SLOTS] += slots;
    if (g->cw[u] >= 127) { g->cum[u][BACKOFF_LONG] += 1; }
}

static void OnAssoc(uint32_t u, Mac48Address)
{
    if (g->assocTime[u] < 0) { g->assocTime[u] = Simulator::Now().GetSeconds(); }
}

static uint32_t QdiscBacklog(Ptr<Node> node, Ptr<NetDevice> dev)
{
    Ptr<TrafficControlLayer> tc = node->GetObject<TrafficControlLayer>();
    if (!tc) { return 0; }
    Ptr<QueueDisc> root = tc->GetRootQueueDiscOnDevice(dev);
    if (!root) { return 0; }
    if (root->GetNQueueDiscClasses() == 0) { return root->GetNPackets(); }
    uint32_t n = 0;
    for (std::size_t i = 0; i < root->GetNQueueDiscClasses(); ++i)
    {
        n += root->GetQueueDiscClass(i)->GetQueueDisc()->GetNPackets();
    }
    return n;
}

static void Snapshot()
{
    const auto& stats = g->monitor->GetFlowStats();
    for (const auto& [flowId, st] : stats)
    {
        Ipv4FlowClassifier::FiveTuple t = g->classifier->FindFlow(flowId);
        auto it = g->ipToUser.find(t.sourceAddress);
        if (it == g->ipToUser.end()) { continue; }
        uint32_t u = it->second;
        g->cum[u][TX] = st.txPackets;
        g->cum[u][RX] = st.rxPackets;
        g->cum[u][DELAY_SUM] = st.delaySum.GetSeconds();
    }
    for (uint32_t u = 0; u < g->cum.size(); ++u)
    {
        Ptr<NetDevice> dev = g->staDevs.Get(u);
        g->cum[u][BACKLOG_QDISC] = QdiscBacklog(g->stas.Get(u), dev);
        Ptr<WifiNetDevice> wdev = DynamicCast<WifiNetDevice>(dev);
        g->cum[u][BACKLOG_MAC] = wdev->GetMac()->GetTxopQueue(AC_BE)->GetNPackets();
    }
    g->out.push_back(Simulator::Now().GetSeconds());
    for (auto& row : g->cum)
    {
        g->out.insert(g->out.end(), row.begin(), row.end());
        row[MAX_TX_GAP] = 0;
    }
}

// ---------------------------------------------------------------- K access points
// Each user's AP index: the AP-side traces count a PPDU for a user only at that user's own AP
// (on a shared channel the other APs hear it too).
static std::vector<uint32_t> g_userAp;

static void OnFleetApPpduDrop(uint32_t k, Ptr<const WifiPpdu> ppdu, WifiPhyRxfailureReason reason)
{
    Ptr<const WifiPsdu> psdu = ppdu->GetPsdu();
    if (!psdu) { return; }
    auto it = g->macToUser.find(psdu->GetAddr2());
    if (it == g->macToUser.end() || g_userAp[it->second] != k) { return; }
    g->cum[it->second][AP_RX_DROPS] += 1;
    int r = static_cast<int>(reason);
    if (r >= 0 && r < N_PHY_REASONS) { g->cum[it->second][PHY_DROP_BASE + r] += 1; }
}

static void OnFleetApRxBegin(uint32_t k, Ptr<const Packet> packet,
                             RxPowerWattPerChannelBand rxPowersW)
{
    WifiMacHeader header;
    if (packet->PeekHeader(header) == 0 || !header.IsQosData()) { return; }
    auto it = g->macToUser.find(header.GetAddr2());
    if (it == g->macToUser.end() || g_userAp[it->second] != k || rxPowersW.empty()) { return; }
    double watts = 0;
    for (const auto& [band, w] : rxPowersW) { watts = std::max(watts, static_cast<double>(w)); }
    if (watts <= 0) { return; }
    g->cum[it->second][AP_RX_DBM_SUM] += 10.0 * std::log10(watts) + 30.0;
    g->cum[it->second][AP_RX_MPDUS] += 1;
}

// Simulates one case with K access points: AP k at (apX[k], apY[k], apZ[k]) on 20 MHz channel
// channels[k], SSID "tupa" (k = 0) or "tupa-k", and user i a station of AP userAp[i] (its
// SSID; no scanning of the others). APs on the same channel number share one YansWifiChannel
// (they hear and interfere with each other and each other's stations); each other channel
// number is a channel object of its own (no energy crosses between non-overlapping channels).
// AP nodes first, then the stations; RunCase is K = 1. apLossDb (K x U), apApLossDb (K x K) and
// staLossDb (U x U),
// row-major, replace Friis when apLossDb is not empty.
std::vector<double> RunFleetCase(std::vector<double> apX, std::vector<double> apY,
                                 std::vector<double> apZ, std::vector<uint32_t> channels,
                                 std::vector<uint32_t> userAp,
                                 std::vector<double> xs, std::vector<double> ys,
                                 std::vector<double> loads, double userHeight, bool macOnly,
                                 double appStart, std::vector<double> snapshots, uint32_t seed,
                                 uint64_t run, uint32_t packetBytes, double nakagamiM,
                                 std::vector<double> apLossDb, std::vector<double> apApLossDb,
                                 std::vector<double> staLossDb)
{
    const uint32_t k = apX.size();
    const uint32_t n = xs.size();
    if (k == 0 || apY.size() != k || apZ.size() != k || channels.size() != k)
    {
        NS_FATAL_ERROR("one position and one channel per AP");
    }
    if (userAp.size() != n) { NS_FATAL_ERROR("one AP index per user"); }
    for (uint32_t a : userAp)
    {
        if (a >= k) { NS_FATAL_ERROR("AP index out of range"); }
    }
    State state;
    g = &state;
    g_userAp = userAp;
    state.cum.assign(n, std::array<double, NF>{});
    state.assocTime.assign(n, -1.0);
    state.txCount.assign(n, {});
    state.cw.assign(n, 15);
    state.lastTx.assign(n, -1.0);

    RngSeedManager::SetSeed(seed);
    RngSeedManager::SetRun(run);

    NodeContainer aps;
    aps.Create(k);
    state.stas.Create(n);

    MobilityHelper mobility;
    Ptr<ListPositionAllocator> pos = CreateObject<ListPositionAllocator>();
    for (uint32_t a = 0; a < k; ++a) { pos->Add(Vector(apX[a], apY[a], apZ[a])); }
    for (uint32_t i = 0; i < n; ++i) { pos->Add(Vector(xs[i], ys[i], userHeight)); }
    mobility.SetPositionAllocator(pos);
    mobility.SetMobilityModel("ns3::ConstantPositionMobilityModel");
    mobility.Install(aps);
    mobility.Install(state.stas);

    const bool matrixLoss = !apLossDb.empty();
    if (matrixLoss
        && (apLossDb.size() != k * n || apApLossDb.size() != k * k || staLossDb.size() != n * n))
    {
        NS_FATAL_ERROR("apLossDb needs K x U values, apApLossDb K x K and staLossDb U x U");
    }
    // One channel object per distinct channel number, in order of first appearance.
    std::vector<uint32_t> numbers;
    std::vector<uint32_t> channelOfAp(k);
    for (uint32_t a = 0; a < k; ++a)
    {
        auto it = std::find(numbers.begin(), numbers.end(), channels[a]);
        channelOfAp[a] = it - numbers.begin();
        if (it == numbers.end()) { numbers.push_back(channels[a]); }
    }
    std::vector<YansWifiChannelHelper> helpers(numbers.size());
    std::vector<Ptr<YansWifiChannel>> media;
    for (uint32_t c = 0; c < numbers.size(); ++c)
    {
        if (!matrixLoss)
        {
            helpers[c].SetPropagationDelay("ns3::ConstantSpeedPropagationDelayModel");
            helpers[c].AddPropagationLoss("ns3::FriisPropagationLossModel",
                                          "Frequency", DoubleValue(5.18e9));
            helpers[c].AddPropagationLoss("ns3::NakagamiPropagationLossModel",
                                          "m0", DoubleValue(nakagamiM),
                                          "m1", DoubleValue(nakagamiM),
                                          "m2", DoubleValue(nakagamiM));
            media.push_back(helpers[c].Create());
            continue;
        }
        Ptr<MatrixPropagationLossModel> matrix = CreateObject<MatrixPropagationLossModel>();
        for (uint32_t a = 0; a < k; ++a)
        {
            Ptr<MobilityModel> am = aps.Get(a)->GetObject<MobilityModel>();
            for (uint32_t i = 0; i < n; ++i)
            {
                matrix->SetLoss(am, state.stas.Get(i)->GetObject<MobilityModel>(),
                                apLossDb[a * n + i], true);
            }
            for (uint32_t b = a + 1; b < k; ++b)
            {
                matrix->SetLoss(am, aps.Get(b)->GetObject<MobilityModel>(),
                                apApLossDb[a * k + b], true);
            }
        }
        for (uint32_t i = 0; i < n; ++i)
        {
            Ptr<MobilityModel> mi = state.stas.Get(i)->GetObject<MobilityModel>();
            for (uint32_t j = i + 1; j < n; ++j)
            {
                matrix->SetLoss(mi, state.stas.Get(j)->GetObject<MobilityModel>(),
                                staLossDb[i * n + j], true);
            }
        }
        Ptr<NakagamiPropagationLossModel> nakagami =
            CreateObjectWithAttributes<NakagamiPropagationLossModel>(
                "m0", DoubleValue(nakagamiM), "m1", DoubleValue(nakagamiM),
                "m2", DoubleValue(nakagamiM));
        matrix->SetNext(nakagami);
        Ptr<YansWifiChannel> medium = CreateObject<YansWifiChannel>();
        medium->SetPropagationDelayModel(CreateObject<ConstantSpeedPropagationDelayModel>());
        medium->SetPropagationLossModel(matrix);
        media.push_back(medium);
    }

    // A PHY helper per AP (the same attributes for every device; its channel object differs).
    auto phyOf = [&](uint32_t a) {
        YansWifiPhyHelper phy;
        phy.SetChannel(media[channelOfAp[a]]);
        phy.Set("ChannelSettings",
                StringValue("{" + std::to_string(channels[a]) + ", 20, BAND_5GHZ, 0}"));
        phy.Set("TxPowerStart", DoubleValue(20.0));
        phy.Set("TxPowerEnd", DoubleValue(20.0));
        phy.Set("RxSensitivity", DoubleValue(-90.0));
        phy.SetPreambleDetectionModel("ns3::ThresholdPreambleDetectionModel",
                                      "MinimumRssi", DoubleValue(-90.0));
        return phy;
    };
    auto ssidOf = [](uint32_t a) {
        return Ssid(a == 0 ? std::string("tupa") : "tupa-" + std::to_string(a));
    };

    WifiHelper wifi;
    wifi.SetStandard(WIFI_STANDARD_80211ac);
    wifi.SetRemoteStationManager("ns3::IdealWifiManager");

    WifiMacHelper mac;
    for (uint32_t i = 0; i < n; ++i)
    {
        mac.SetType("ns3::StaWifiMac", "Ssid", SsidValue(ssidOf(userAp[i])));
        state.staDevs.Add(wifi.Install(phyOf(userAp[i]), mac, state.stas.Get(i)));
    }
    NetDeviceContainer apDev;
    for (uint32_t a = 0; a < k; ++a)
    {
        mac.SetType("ns3::ApWifiMac", "Ssid", SsidValue(ssidOf(a)));
        apDev.Add(wifi.Install(phyOf(a), mac, aps.Get(a)));
    }

    NetDeviceContainer all;
    all.Add(apDev);
    all.Add(state.staDevs);
    int64_t stream = 1000;
    stream += WifiHelper::AssignStreams(all, stream);
    for (uint32_t c = 0; c < media.size(); ++c)
    {
        stream += matrixLoss ? media[c]->AssignStreams(stream)
                             : helpers[c].AssignStreams(media[c], stream);
    }

    InternetStackHelper internet;
    internet.Install(aps);
    internet.Install(state.stas);
    NodeContainer allNodes(aps, state.stas);
    stream += internet.AssignStreams(allNodes, stream);
    Ipv4AddressHelper address;
    address.SetBase("10.1.0.0", "255.255.0.0");
    Ipv4InterfaceContainer apIf = address.Assign(apDev);
    Ipv4InterfaceContainer staIf = address.Assign(state.staDevs);
    if (macOnly)
    {
        TrafficControlHelper tch;
        tch.Uninstall(apDev);
        tch.Uninstall(state.staDevs);
    }

    const uint16_t port = 9;
    PacketSinkHelper sink("ns3::UdpSocketFactory",
                          InetSocketAddress(Ipv4Address::GetAny(), port));
    ApplicationContainer sinkApp = sink.Install(aps);
    sinkApp.Start(Seconds(0.0));

    Ptr<UniformRandomVariable> jitter = CreateObject<UniformRandomVariable>();
    jitter->SetAttribute("Min", DoubleValue(0.0));
    jitter->SetAttribute("Max", DoubleValue(0.005));
    jitter->SetStream(stream++);

    for (uint32_t i = 0; i < n; ++i)
    {
        Ptr<Node> node = state.stas.Get(i);
        Ptr<NetDevice> dev = state.staDevs.Get(i);
        Ptr<WifiNetDevice> wdev = DynamicCast<WifiNetDevice>(dev);
        state.macToUser[Mac48Address::ConvertFrom(dev->GetAddress())] = i;
        state.ipToUser[staIf.GetAddress(i)] = i;
        Ptr<WifiMac> wmac = wdev->GetMac();
        wmac->TraceConnectWithoutContext("DroppedMpdu", MakeBoundCallback(&OnDropped, i));
        wmac->TraceConnectWithoutContext("MacTxDrop", MakeBoundCallback(&OnMacTxDrop, i));
        wmac->TraceConnectWithoutContext("NAckedMpdu", MakeBoundCallback(&OnNacked, i));
        wmac->TraceConnectWithoutContext("AckedMpdu", MakeBoundCallback(&OnAcked, i));
        wmac->TraceConnectWithoutContext("MpduResponseTimeout",
                                         MakeBoundCallback(&OnMpduTimeout, i));
        wmac->TraceConnectWithoutContext("PsduResponseTimeout",
                                         MakeBoundCallback(&OnPsduTimeout, i));
        wmac->TraceConnectWithoutContext("Assoc", MakeBoundCallback(&OnAssoc, i));
        Ptr<QosTxop> be = wmac->GetQosTxop(AC_BE);
        be->TraceConnectWithoutContext("CwTrace", MakeBoundCallback(&OnCw, i));
        be->TraceConnectWithoutContext("BackoffTrace", MakeBoundCallback(&OnBackoff, i));
        wdev->GetPhy()->TraceConnectWithoutContext("PhyTxPsduBegin",
                                                   MakeBoundCallback(&OnPsduTx, i));
        Ptr<TrafficControlLayer> tc = node->GetObject<TrafficControlLayer>();
        tc->TraceConnectWithoutContext("TcDrop", MakeBoundCallback(&OnTcDrop, i));
        Ptr<QueueDisc> root = tc->GetRootQueueDiscOnDevice(dev);
        if (root)
        {
            root->TraceConnectWithoutContext("Drop", MakeBoundCallback(&OnQdiscDrop, i));
        }
        Ptr<Ipv4L3Protocol> ipv4 = node->GetObject<Ipv4L3Protocol>();
        ipv4->TraceConnectWithoutContext("Drop", MakeBoundCallback(&OnIpDrop, i));
        int32_t ifIndex = ipv4->GetInterfaceForDevice(dev);
        ipv4->GetInterface(ifIndex)->GetArpCache()->TraceConnectWithoutContext(
            "Drop", MakeBoundCallback(&OnArpDrop, i));
        node->GetObject<ArpL3Protocol>()->TraceConnectWithoutContext(
            "Drop", MakeBoundCallback(&OnArpDrop, i));

        if (loads[i] <= 0) { continue; }
        OnOffHelper onoff("ns3::UdpSocketFactory",
                          InetSocketAddress(apIf.GetAddress(userAp[i]), port));
        onoff.SetAttribute("OnTime", StringValue("ns3::ConstantRandomVariable[Constant=1e6]"));
        onoff.SetAttribute("OffTime", StringValue("ns3::ConstantRandomVariable[Constant=0]"));
        onoff.SetAttribute("DataRate", DataRateValue(DataRate(static_cast<uint64_t>(loads[i]))));
        onoff.SetAttribute("PacketSize", UintegerValue(packetBytes));
        ApplicationContainer app = onoff.Install(node);
        stream += onoff.AssignStreams(node, stream);
        app.Start(Seconds(appStart + jitter->GetValue()));
        app.Get(0)->TraceConnectWithoutContext("Tx", MakeBoundCallback(&OnAppTx, i));
    }
    for (uint32_t a = 0; a < k; ++a)
    {
        Ptr<WifiPhy> apPhy = DynamicCast<WifiNetDevice>(apDev.Get(a))->GetPhy();
        apPhy->TraceConnectWithoutContext("PhyRxPpduDrop",
                                          MakeBoundCallback(&OnFleetApPpduDrop, a));
        apPhy->TraceConnectWithoutContext("PhyRxBegin", MakeBoundCallback(&OnFleetApRxBegin, a));
    }

    FlowMonitorHelper flowmon;
    state.monitor = flowmon.InstallAll();
    state.classifier = DynamicCast<Ipv4FlowClassifier>(flowmon.GetClassifier());

    double last = 0;
    for (double t : snapshots)
    {
        Simulator::Schedule(Seconds(t), &Snapshot);
        last = std::max(last, t);
    }
    Simulator::Stop(Seconds(last) + NanoSeconds(1));
    Simulator::Run();

    std::vector<double> result = state.out;
    result.insert(result.end(), state.assocTime.begin(), state.assocTime.end());
    state.monitor = nullptr;
    state.classifier = nullptr;
    Simulator::Destroy();
    Ipv4AddressGenerator::Reset();
    g = nullptr;
    g_userAp.clear();
    return result;
}

// Simulates one case; returns [n_snapshots x (1 + U x NF)] then U association times (-1: never).
// apLossDb empty: Friis (the open environment). Otherwise apLossDb (U) is each user's loss to
// the AP and staLossDb (U x U, row-major) the loss between users, set in a
// MatrixPropagationLossModel (symmetric) ahead of the same Nakagami fading.
std::vector<double> RunCase(double uavX, double uavY, double uavZ,
                            std::vector<double> xs, std::vector<double> ys,
                            std::vector<double> loads, double userHeight, bool macOnly,
                            double appStart, std::vector<double> snapshots, uint32_t seed,
                            uint64_t run, uint32_t packetBytes, double nakagamiM,
                            std::vector<double> apLossDb, std::vector<double> staLossDb)
{
    // One AP on channel 36, every user its station: RunFleetCase with K = 1.
    std::vector<double> apApLossDb;
    if (!apLossDb.empty()) { apApLossDb.assign(1, 0.0); }
    return RunFleetCase({uavX}, {uavY}, {uavZ}, {36u}, std::vector<uint32_t>(xs.size(), 0u),
                        xs, ys, loads, userHeight, macOnly, appStart, snapshots, seed, run,
                        packetBytes, nakagamiM, apLossDb, apApLossDb, staLossDb);
}
}  // namespace tupa_ns3
