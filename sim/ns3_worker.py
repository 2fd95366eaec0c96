"""The ns-3 side of the ns-3 backend: runs in a child process, never in the caller's.

``python -m sim.ns3_worker REQUEST_FD REPLY_FD [NICENESS]`` imports ns-3 (its Python bindings
go through cppyy: ~15 s the first time), compiles the case scenario (C++,
``sim/ns3_worker.cc``, JIT-compiled by cling, a few seconds), tells the parent it is ready,
then simulates one case per request until its request pipe closes. The protocol is one JSON
object per line on each pipe:

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
from pathlib import Path
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

CPP_SOURCE = Path(__file__).with_name("ns3_worker.cc")
"""The scenario ``RunCase`` in C++ (``namespace tupa_ns3``), compiled by cppyy on load: a file of
its own (package data), so that an editor and a compiler see C++."""


def _load() -> Any:
    """Import ns-3 and compile the scenario; returns the compiled ``RunCase``."""
    import cppyy
    from ns import ns  # noqa: F401  (loads the ns-3 libraries and headers into cppyy)

    cppyy.cppdef(CPP_SOURCE.read_text())
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
