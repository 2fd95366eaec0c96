"""The ns-3 side of the ns-3 backend: runs in a child process, never in the caller's.

``python -m sim.ns3_worker REQUEST_FD REPLY_FD [NICENESS]`` imports ns-3 (its Python bindings
go through cppyy: ~15 s the first time), compiles the case scenario below (C++, JIT-compiled by
cling, a few seconds), tells the parent it is ready, then simulates one case per request until
its request pipe closes. The protocol is one JSON object per line on each pipe:

* request ``{"case": {...}, "queueing": ..., ...}`` → reply ``{"ok": true, "snapshots": ...}``
  or ``{"ok": false, "error": "..."}`` (a Python exception while setting up the case);
* a crash (segfault, abort inside ns-3) or a hang shows up in the parent as a closed pipe or a
  timeout: :mod:`sim.ns3_backend` reports which case failed and starts a fresh worker.

The scenario is written in C++ so that ns-3 owns every object it creates (no Python
reference keeps a node alive across ``Simulator::Destroy``) and the trace sinks cost nothing
in Python. Between cases it destroys the simulator (which also empties the node list) and
resets the global IPv4 address generator, so each case starts from the same state.

Everything the network is made of, with the ns-3 3.44 attribute names (see
docs/network-model.md):

* AP–STA infrastructure, ``WIFI_STANDARD_80211ac``, ``WifiPhy::ChannelSettings`` =
  ``{36, 20, BAND_5GHZ, 0}``, ``TxPowerStart`` = ``TxPowerEnd`` = 20 dBm, ``RxNoiseFigure``
  7 dB (default), ``RxSensitivity`` −90 dBm, ``ThresholdPreambleDetectionModel::MinimumRssi``
  −90 dBm (its SNR ``Threshold`` stays 4 dB), ``TableBasedErrorRateModel`` (default);
* ``YansWifiChannel``: ``ConstantSpeedPropagationDelayModel``, then
  ``FriisPropagationLossModel`` (``Frequency`` 5.18 GHz), then ``NakagamiPropagationLossModel``
  with ``m0`` = ``m1`` = ``m2`` = 10.73 (Rician K = 13 dB: m = (K + 1)² / (2K + 1)), drawn
  per packet and receiver;
* ``IdealWifiManager`` (default ``BerThreshold`` 1e-6), long guard interval, no RTS/CTS,
  A-MPDU up to 65,535 bytes, A-MSDU off, ``WifiMacQueue`` 500 packets / ``MaxDelay`` 500 ms
  (defaults);
* queueing ``fq-codel``: the queue disc ``Ipv4AddressHelper::Assign`` installs (an
  ``MqQueueDisc`` with one ``FqCoDelQueueDisc`` per access category) is left in place;
  ``mac-only``: ``TrafficControlHelper::Uninstall`` on every device;
* traffic: one ``OnOffApplication`` per user (always on: CBR at the user's load, 512-byte UDP
  payloads) to a ``PacketSink`` on the AP; users start at the association time plus a
  uniform 0–5 ms jitter; users with zero load send nothing;
* channel in an urban environment (the request carries ``ap_loss_db`` and ``sta_loss_db``):
  ``MatrixPropagationLossModel`` with those per-pair losses (symmetric) in place of Friis, then
  the same Nakagami model; see :mod:`sim.ns3_backend` for where the losses come from;
* K access points (``RunFleetCase``, a request with a ``fleet`` entry): K AP nodes, AP k with
  SSID ``tupa`` (k = 0) or ``tupa-k`` and its stations (the request says which) with the same
  SSID; APs on the same channel number share one ``YansWifiChannel``, each other channel number
  gets its own (distinct 20 MHz channels: no energy crosses); everything else as above. One AP
  (``RunCase``) is this with K = 1 on channel 36: one scenario for both. The AP-side counters
  of a user count only its own AP's receptions;
* measurement: ``FlowMonitor`` on all nodes for transmitted / received packets and delay; drop
  counters from trace sources (queue disc ``Drop``, ``WifiMac::DroppedMpdu`` by reason,
  ``WifiMac::MacTxDrop``, ``ArpCache::Drop`` and ``ArpL3Protocol::Drop``: where the packets of a
  station that never associated end, ``Ipv4L3Protocol::Drop``); the AP's received power per
  STA (``PhyRxBegin``, one sample per data MPDU whose reception starts); cumulative counters
  are copied at each snapshot time so the parent can take differences over any window.
"""

from __future__ import annotations

import json
import os
import sys
import time
import traceback
from typing import Any

# Counters per user and snapshot (cumulative since the start, except the two backlogs, which
# are instantaneous). The names are the keys the parent sees; keep in step with the C++ enum.
FIELDS: tuple[str, ...] = (
    "tx_pkts",  # FlowMonitor: IP packets sent by the user's flow
    "rx_pkts",  # FlowMonitor: received at the AP
    "delay_sum_s",  # FlowMonitor: sum of one-way delays of the received packets
    "drop_qdisc",  # queue disc (FqCoDel) drops
    "drop_mac_failed_enqueue",  # WifiMac::DroppedMpdu WIFI_MAC_DROP_FAILED_ENQUEUE (queue full)
    "drop_mac_expired",  # ... WIFI_MAC_DROP_EXPIRED_LIFETIME (waited > MaxDelay 500 ms)
    "drop_mac_retry_limit",  # ... WIFI_MAC_DROP_REACHED_RETRY_LIMIT
    "drop_mac_old_packet",  # ... WIFI_MAC_DROP_QOS_OLD_PACKET
    "drop_mac_tx",  # WifiMac::MacTxDrop (e.g. not associated)
    "drop_arp",  # ArpCache::Drop and ArpL3Protocol::Drop (address never resolved, pending
    # queue (3 packets) full while resolving: the packets of a station that never associated)
    "drop_tc",  # TrafficControlLayer::TcDrop: no queue disc and the MAC queue (500) is full
    "backlog_qdisc_pkts",  # packets in the queue disc now
    "backlog_mac_pkts",  # packets in the BE WifiMacQueue now (in flight included)
    "data_ppdus",  # data PPDUs the STA started to transmit (retransmissions included)
    "data_mpdus",  # data MPDUs in them
    "mcs_mpdu_sum",  # sum of the MCS index over those MPDUs
    "nacked_mpdus",  # WifiMac::NAckedMpdu (not acknowledged, will be retried or dropped)
    "response_timeouts",  # WifiMac::{Mpdu,Psdu}ResponseTimeout (no Ack / Block Ack came)
    "ap_rx_ppdu_drops",  # PPDUs from this STA the AP's PHY dropped (any reason)
    "app_tx_pkts",  # OnOffApplication::Tx
    "acked_mpdus",  # WifiMac::AckedMpdu
    "ampdu_max_mpdus",  # largest A-MPDU (MPDUs) seen so far
    "expired_unsent",  # MPDUs dropped at MaxDelay that had never been transmitted
    "expired_tx_sum",  # transmissions of the MPDUs dropped at MaxDelay, summed
    "old_tx_sum",  # transmissions of the MPDUs dropped as QOS_OLD_PACKET, summed
    "tx_per_mpdu_sum",  # transmissions of the acknowledged MPDUs, summed
    "backoff_draws",  # BE Txop BackoffTrace: backoffs drawn
    "backoff_slots_sum",  # slots drawn, summed
    "backoff_long_draws",  # backoffs drawn with CW >= 127 (after 3+ failures in a row)
    "max_tx_gap_s",  # longest gap between data PPDUs since the previous snapshot (not summed)
    "ap_rx_dbm_sum",  # WifiPhy::PhyRxBegin at the AP: received power (dBm) of this STA's
    "ap_rx_mpdus",  # data MPDUs, summed, and how many (their mean is the channel ns-3 applied)
    "drop_ip",  # Ipv4L3Protocol::Drop on the user's node (e.g. a station that never associated)
)
# AP PHY drops of this STA's PPDUs by ns3::WifiPhyRxfailureReason (25 values in ns-3 3.44).
PHY_DROP_REASONS: tuple[str, ...] = (
    "UNKNOWN",
    "UNSUPPORTED_SETTINGS",
    "CHANNEL_SWITCHING",
    "RXING",
    "TXING",
    "SLEEPING",
    "POWERED_OFF",
    "TRUNCATED_TX",
    "BUSY_DECODING_PREAMBLE",
    "PREAMBLE_DETECT_FAILURE",
    "RECEPTION_ABORTED_BY_TX",
    "L_SIG_FAILURE",
    "HT_SIG_FAILURE",
    "SIG_A_FAILURE",
    "SIG_B_FAILURE",
    "U_SIG_FAILURE",
    "EHT_SIG_FAILURE",
    "PREAMBLE_DETECTION_PACKET_SWITCH",
    "FRAME_CAPTURE_PACKET_SWITCH",
    "OBSS_PD_CCA_RESET",
    "PPDU_TOO_LATE",
    "FILTERED",
    "DMG_HEADER_FAILURE",
    "DMG_ALLOCATION_ENDED",
    "SIGNAL_DETECTION_ABORTED_BY_TX",
)
N_FIELDS = len(FIELDS) + len(PHY_DROP_REASONS)

_CPP = r"""
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
"""


def _load() -> Any:
    """Import ns-3 and compile the scenario; returns the compiled ``RunCase``."""
    import cppyy
    from ns import ns  # noqa: F401  (loads the ns-3 libraries and headers into cppyy)

    cppyy.cppdef(_CPP)
    return cppyy.gbl.tupa_ns3.RunCase


def simulate(run_case: Any, request: dict[str, Any]) -> dict[str, Any]:
    """Simulate one case described by ``request`` (see :func:`sim.ns3_backend._request`).

    Returns ``{"snapshots": [{"time_s", "users": [{field: value}]}], "assoc_time_s": [...]}``
    with cumulative counters at each snapshot time.
    """
    import cppyy

    case = request["case"]
    users = case["users"]
    n_users = len(users)
    snapshot_times = [float(t) for t in request["snapshot_times_s"]]
    vec = cppyy.gbl.std.vector["double"]
    flat = run_case(
        float(case["uav"]["x_m"]),
        float(case["uav"]["y_m"]),
        float(case["uav"]["z_m"]),
        *_users_and_protocol(request, snapshot_times),
        vec([float(x) for x in request.get("ap_loss_db", [])]),
        vec([float(x) for x in request.get("sta_loss_db", [])]),
    )
    return _unpack(flat, n_users, len(snapshot_times))


def _users_and_protocol(request: dict[str, Any], snapshot_times: list[float]) -> tuple:
    """The arguments ``RunCase`` and ``RunFleetCase`` share, in their order: the users'
    positions and loads, then the protocol (user height to Nakagami m)."""
    import cppyy

    vec = cppyy.gbl.std.vector["double"]
    users = request["case"]["users"]
    return (
        vec([float(u["x_m"]) for u in users]),
        vec([float(u["y_m"]) for u in users]),
        vec([float(u["load_bps"]) for u in users]),
        float(request["user_height_m"]),
        request["queueing"] == "mac-only",
        float(request["app_start_s"]),
        vec(snapshot_times),
        int(request["seed"]),
        int(request["run"]),
        int(request["packet_bytes"]),
        float(request["nakagami_m"]),
    )


def simulate_fleet(run_fleet_case: Any, request: dict[str, Any]) -> dict[str, Any]:
    """Simulate one case with K access points (``request["fleet"]``: ``uavs`` [[x, y, z]] and
    ``channels`` per AP, ``association`` per user; see :func:`sim.ns3_backend._fleet_request`)
    with the compiled ``RunFleetCase``; the reply is :func:`simulate`'s."""
    import cppyy

    case = request["case"]
    fleet = request["fleet"]
    users = case["users"]
    snapshot_times = [float(t) for t in request["snapshot_times_s"]]
    vec = cppyy.gbl.std.vector["double"]
    uvec = cppyy.gbl.std.vector["unsigned int"]
    uavs = fleet["uavs"]
    flat = run_fleet_case(
        vec([float(p[0]) for p in uavs]),
        vec([float(p[1]) for p in uavs]),
        vec([float(p[2]) for p in uavs]),
        uvec([int(c) for c in fleet["channels"]]),
        uvec([int(a) for a in fleet["association"]]),
        *_users_and_protocol(request, snapshot_times),
        vec([float(x) for x in request.get("ap_loss_db", [])]),
        vec([float(x) for x in request.get("ap_ap_loss_db", [])]),
        vec([float(x) for x in request.get("sta_loss_db", [])]),
    )
    return _unpack(flat, len(users), len(snapshot_times))


def _unpack(flat: Any, n_users: int, n_snapshots: int) -> dict[str, Any]:
    """The flat vector a scenario returns as snapshots of named counters per user."""
    values = list(flat)
    row = 1 + n_users * N_FIELDS
    names = FIELDS + tuple(f"ap_phy_drop_{r.lower()}" for r in PHY_DROP_REASONS)
    snapshots = []
    for k in range(n_snapshots):
        block = values[k * row : (k + 1) * row]
        snapshots.append(
            {
                "time_s": block[0],
                "users": [
                    dict(zip(names, block[1 + u * N_FIELDS : 1 + (u + 1) * N_FIELDS], strict=True))
                    for u in range(n_users)
                ],
            }
        )
    assoc = values[n_snapshots * row :]
    return {"snapshots": snapshots, "assoc_time_s": assoc}


def serve(request_fd: int, reply_fd: int) -> None:
    """Answer requests (JSON lines on ``request_fd``) until it closes."""
    requests = os.fdopen(request_fd, "r", encoding="utf-8")
    replies = os.fdopen(reply_fd, "w", encoding="utf-8")

    def reply(obj: dict[str, Any]) -> None:
        replies.write(json.dumps(obj) + "\n")
        replies.flush()

    started = time.perf_counter()
    try:
        run_case = _load()
    except Exception:  # the parent reports it; nothing else to do here
        reply({"ok": False, "error": "ns-3 set-up failed: " + traceback.format_exc(limit=3)})
        return
    from importlib.metadata import version

    reply({"ok": True, "ready": True, "load_s": time.perf_counter() - started,
           "ns3_version": version("ns3")})  # fmt: skip
    for line in requests:
        request = json.loads(line)
        started = time.perf_counter()
        try:
            if "fleet" in request:
                import cppyy

                result = simulate_fleet(cppyy.gbl.tupa_ns3.RunFleetCase, request)
            else:
                result = simulate(run_case, request)
        except Exception:
            reply({"ok": False, "error": traceback.format_exc(limit=3)})
            continue
        result["ok"] = True
        result["wall_s"] = time.perf_counter() - started
        reply(result)


if __name__ == "__main__":
    if len(sys.argv) not in (3, 4):
        sys.exit("usage: python -m sim.ns3_worker REQUEST_FD REPLY_FD [NICENESS]")
    if len(sys.argv) == 4 and int(sys.argv[3]) > 0:
        os.nice(int(sys.argv[3]))
    serve(int(sys.argv[1]), int(sys.argv[2]))
