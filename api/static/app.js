// TUPA operator view: draws the frames the service streams from GET /v1/live/events.
//
// No library and no build step. The stream is read with fetch() so that the token travels in the
// Authorization header (EventSource cannot send one, and a token in a URL ends up in logs); the
// Server-Sent Events are parsed here, and the page reconnects by itself with a backoff (after a
// service restart, a network blip, or a stream that went quiet). The token is asked once and
// kept in this tab's sessionStorage. Every text from the service goes in with textContent.
//
// The frame's shape is described in service/live_view.py. Map units are metres in the area
// frame (x east, y north); SVG's y points down, so y is flipped (north up).
"use strict";

(() => {
  const TOKEN_KEY = "tupa.token";
  const STREAM_URL = "/v1/live/events";
  const STALL_MS = 45000; // three missed keep-alives (15 s each): reconnect
  const BACKOFF_MIN_MS = 500;
  const BACKOFF_MAX_MS = 10000;
  const MAX_BUFFER_CHARS = 8 * 1024 * 1024;
  const MARGIN_M = 26;
  const CHART_SPAN_S = 300;
  const TABLE_ROWS = 12;
  const SVG_NS = "http://www.w3.org/2000/svg";
  const LINK_WORDS = { up: "up", connecting: "connecting", link_lost: "lost" };
  const VEHICLE_COLOURS = ["#4fb3ff", "#7ee787", "#ff9bd2", "#f2cc60"];

  // Read by the browser test and the benchmark: counters and the last frame, never the token.
  const view = {
    frames: 0,
    firstFrameMs: null, // performance.now() at the first frame: ms since navigation start
    connection: "connecting",
    reconnects: 0,
    frame: null,
  };
  window.tupaView = view;

  const $ = (id) => document.getElementById(id);

  function el(tag, attrs = {}, parent = null) {
    const node = document.createElementNS(SVG_NS, tag);
    for (const [name, value] of Object.entries(attrs)) node.setAttribute(name, value);
    if (parent) parent.appendChild(node);
    return node;
  }

  const sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms));
  const fmt = (value, digits = 1) =>
    value === null || value === undefined ? "–" : Number(value).toFixed(digits);
  const mbps = (bps) => `${(bps / 1e6).toFixed(1)} Mbit/s`;
  const clamp = (v, lo, hi) => Math.min(hi, Math.max(lo, v));

  // ------------------------------------------------------------------ token

  function askToken(message) {
    const dialog = $("token-dialog");
    const form = $("token-form");
    const input = $("token-input");
    if (message) $("token-message").textContent = message;
    setConnection("token", "token needed");
    return new Promise((resolve) => {
      const submitted = (event) => {
        event.preventDefault();
        const value = input.value.trim();
        if (!value) return;
        sessionStorage.setItem(TOKEN_KEY, value);
        input.value = "";
        form.removeEventListener("submit", submitted);
        dialog.close();
        resolve();
      };
      form.addEventListener("submit", submitted);
      if (!dialog.open) dialog.showModal();
      input.focus();
    });
  }

  // ------------------------------------------------------------------ the stream

  function setConnection(state, text) {
    view.connection = state;
    document.body.dataset.connection = state; // the map dims while it is not live
    const badge = $("connection");
    badge.dataset.state = state;
    badge.textContent = text;
  }

  function parseEvent(block) {
    let type = "message";
    const data = [];
    for (const line of block.split("\n")) {
      if (!line || line.startsWith(":")) continue; // a comment: the keep-alive
      const colon = line.indexOf(":");
      const field = colon < 0 ? line : line.slice(0, colon);
      let value = colon < 0 ? "" : line.slice(colon + 1);
      if (value.startsWith(" ")) value = value.slice(1);
      if (field === "event") type = value;
      else if (field === "data") data.push(value);
    }
    return data.length ? { type, data: data.join("\n") } : null;
  }

  // One connection: resolves when it ends, saying how (never rejects).
  async function streamOnce() {
    const controller = new AbortController();
    let watchdog = null;
    const kick = () => {
      clearTimeout(watchdog);
      watchdog = setTimeout(() => controller.abort(), STALL_MS);
    };
    let gotFrames = false;
    try {
      kick();
      const response = await fetch(STREAM_URL, {
        headers: {
          Authorization: `Bearer ${sessionStorage.getItem(TOKEN_KEY)}`,
          Accept: "text/event-stream",
        },
        cache: "no-store",
        signal: controller.signal,
      });
      if (response.status === 401) return { unauthorized: true };
      if (!response.ok || !response.body) {
        const retryAfter = Number(response.headers.get("Retry-After"));
        return { retryAfterMs: retryAfter > 0 ? retryAfter * 1000 : 0 };
      }
      const reader = response.body.pipeThrough(new TextDecoderStream()).getReader();
      let buffer = "";
      for (;;) {
        const { value, done } = await reader.read();
        if (done) break;
        kick();
        buffer += value.replace(/\r\n?/g, "\n"); // the service sends LF; be lenient
        if (buffer.length > MAX_BUFFER_CHARS) break;
        let end;
        while ((end = buffer.indexOf("\n\n")) >= 0) {
          const event = parseEvent(buffer.slice(0, end));
          buffer = buffer.slice(end + 2);
          if (event && event.type === "frame") {
            onFrame(JSON.parse(event.data));
            if (!gotFrames) setConnection("live", "live");
            gotFrames = true;
          }
        }
      }
    } catch (error) {
      if (error.name !== "AbortError") console.warn("live stream:", error.message);
    } finally {
      clearTimeout(watchdog);
      controller.abort();
    }
    return { gotFrames };
  }

  async function run() {
    let backoff = BACKOFF_MIN_MS;
    for (;;) {
      if (!sessionStorage.getItem(TOKEN_KEY)) await askToken();
      setConnection("connecting", "connecting");
      const outcome = await streamOnce();
      if (outcome.unauthorized) {
        sessionStorage.removeItem(TOKEN_KEY);
        await askToken("The service refused that token: enter it again.");
        backoff = BACKOFF_MIN_MS;
        continue;
      }
      if (outcome.gotFrames) backoff = BACKOFF_MIN_MS;
      const jittered = backoff * (0.75 + Math.random() * 0.5);
      const waitMs = Math.max(outcome.retryAfterMs || 0, jittered);
      setConnection("reconnecting", `reconnecting in ${Math.ceil(waitMs / 1000)} s`);
      view.reconnects += 1;
      await sleep(waitMs);
      backoff = Math.min(backoff * 2, BACKOFF_MAX_MS);
    }
  }

  // ------------------------------------------------------------------ frames

  function onFrame(frame) {
    view.frames += 1;
    view.frame = frame;
    view.receivedAt = performance.now();
    if (view.firstFrameMs === null) view.firstFrameMs = view.receivedAt;
    render(frame);
  }

  let areaKey = null;
  let H = 500;
  const Y = (y) => H - y; // north up
  const users = new Map(); // id -> {circle, title, label}
  const vehicles = new Map(); // id -> {group, body, label, track, target, line}

  function render(frame) {
    const key = JSON.stringify([frame.area, frame.geofence]);
    if (key !== areaKey) {
      areaKey = key;
      drawArea(frame.area, frame.geofence);
    }
    const delayRef = frame.utility ? frame.utility.delay_ref_s : 1;
    $("delay-ref").textContent = fmt(delayRef, 1);
    drawUsers(frame.users, delayRef);
    drawVehicles(frame.vehicles);
    $("policy").textContent = frame.policy.name;
    renderVehicleCards(frame.vehicles);
    renderUtility(frame.utility, frame.utility_history);
    renderUsersTable(frame.users, delayRef);
    tick();
  }

  function drawArea(area, fence) {
    const map = $("map");
    const W = area.size_x_m;
    H = area.size_y_m;
    map.setAttribute(
      "viewBox",
      `${-MARGIN_M} ${-MARGIN_M} ${W + 2 * MARGIN_M} ${H + 2 * MARGIN_M}`,
    );
    const grid = $("layer-grid");
    grid.replaceChildren();
    grid.setAttribute("class", "grid");
    const major = 100;
    for (let x = 0; x <= W + 1e-6; x += area.zone_m) {
      const isMajor = Math.abs(x % major) < 1e-6;
      el("line", { x1: x, y1: 0, x2: x, y2: H, class: isMajor ? "major" : "" }, grid);
      if (isMajor) el("text", { x, y: H + 14, "text-anchor": "middle" }, grid).textContent = x;
    }
    for (let y = 0; y <= H + 1e-6; y += area.zone_m) {
      const isMajor = Math.abs(y % major) < 1e-6;
      el("line", { x1: 0, y1: Y(y), x2: W, y2: Y(y), class: isMajor ? "major" : "" }, grid);
      if (isMajor) {
        el("text", { x: -5, y: Y(y) + 3, "text-anchor": "end" }, grid).textContent = y;
      }
    }
    const fenceLayer = $("layer-geofence");
    fenceLayer.replaceChildren();
    const [x0, x1] = fence.x_m;
    const [y0, y1] = fence.y_m;
    el("rect", { x: x0, y: Y(y1), width: x1 - x0, height: y1 - y0, class: "fence" }, fenceLayer);
    const label = el("text", { x: x0 + 4, y: Y(y1) - 6, class: "fence-label" }, fenceLayer);
    label.textContent =
      `geofence ${x0}–${x1} × ${y0}–${y1} m, altitude ${fence.z_m[0]}–${fence.z_m[1]} m · ` +
      `zones ${area.zone_m} m · north ↑`;
  }

  // Circle area proportional to the offered load: 4 m plus 4 m per sqrt(Mbit/s).
  const userRadius = (bps) => clamp(4 + 4 * Math.sqrt(Math.max(bps, 0) / 1e6), 4, 40);

  // How well a user is served, 0 (bad) to 1 (good): the worse of throughput/offered and
  // 1 - delay/delay_ref.
  const quality = (user, delayRef) =>
    clamp(Math.min(user.served, 1 - user.delay_s / delayRef), 0, 1);
  const qualityColour = (q) => `hsl(${Math.round(120 * q)} 70% 48%)`;

  function drawUsers(list, delayRef) {
    const layer = $("layer-users");
    const seen = new Set();
    const labelled = list.length <= 40;
    for (const user of list) {
      seen.add(user.id);
      let marker = users.get(user.id);
      if (!marker) {
        const circle = el("circle", { class: "user" }, layer);
        circle.dataset.userId = user.id;
        const title = el("title", {}, circle);
        const label = el("text", { class: "user-label" }, layer);
        marker = { circle, title, label };
        users.set(user.id, marker);
      }
      const r = userRadius(user.offered_bps);
      const q = quality(user, delayRef);
      marker.circle.setAttribute("cx", user.x_m);
      marker.circle.setAttribute("cy", Y(user.y_m));
      marker.circle.setAttribute("r", r.toFixed(2));
      marker.circle.setAttribute("fill", qualityColour(q));
      marker.circle.dataset.offered = user.offered_bps;
      marker.title.textContent =
        `${user.id}: offered ${mbps(user.offered_bps)}, throughput ${mbps(user.throughput_bps)}` +
        ` (${Math.round(100 * user.served)} %), delay ${fmt(user.delay_s * 1000, 0)} ms,` +
        ` loss ${fmt(100 * user.plr, 1)} %`;
      marker.label.setAttribute("x", user.x_m + r + 2);
      marker.label.setAttribute("y", Y(user.y_m) + 3);
      marker.label.textContent = labelled ? user.id : "";
    }
    for (const [id, marker] of users) {
      if (!seen.has(id)) {
        marker.circle.remove();
        marker.label.remove();
        users.delete(id);
      }
    }
  }

  // Degrees clockwise from north: the vehicle's own heading, else its direction of travel.
  function headingOf(vehicle) {
    if (vehicle.heading_deg !== null && vehicle.heading_deg !== undefined) {
      return vehicle.heading_deg;
    }
    const track = vehicle.track_m;
    const here = vehicle.position_m;
    for (let i = track.length - 1; i >= 0 && here; i -= 1) {
      const dx = here[0] - track[i][0];
      const dy = here[1] - track[i][1];
      if (Math.hypot(dx, dy) > 1) return (Math.atan2(dx, dy) * 180) / Math.PI;
    }
    return 0;
  }

  function drawVehicles(list) {
    const seen = new Set();
    list.forEach((vehicle, index) => {
      seen.add(vehicle.id);
      let drawn = vehicles.get(vehicle.id);
      const colour = VEHICLE_COLOURS[index % VEHICLE_COLOURS.length];
      if (!drawn) {
        const track = el("polyline", { class: "track", stroke: colour }, $("layer-tracks"));
        const targets = $("layer-targets");
        const line = el("line", { class: "target-line" }, targets);
        const target = el("g", { class: "target" }, targets);
        el("circle", { r: 7, class: "target-mark" }, target);
        el("line", { x1: -11, y1: 0, x2: 11, y2: 0, class: "target-mark" }, target);
        el("line", { x1: 0, y1: -11, x2: 0, y2: 11, class: "target-mark" }, target);
        const group = el("g", { class: "vehicle" }, $("layer-vehicles"));
        group.dataset.vehicleId = vehicle.id;
        const body = el("polygon", { points: "0,-11 8,9 0,4.5 -8,9", class: "vehicle-body" }, group);
        group.style.setProperty("--vehicle-colour", colour);
        const label = el("text", { class: "vehicle-label" }, $("layer-vehicles"));
        drawn = { group, body, label, track, target, line };
        vehicles.set(vehicle.id, drawn);
      }
      const p = vehicle.position_m;
      const shown = p !== null;
      for (const node of [drawn.group, drawn.label, drawn.line]) {
        node.style.display = shown ? "" : "none";
      }
      drawn.group.dataset.link = vehicle.link;
      if (shown) {
        const heading = headingOf(vehicle);
        drawn.group.setAttribute(
          "transform",
          `translate(${p[0]} ${Y(p[1])}) rotate(${heading.toFixed(1)})`,
        );
        drawn.group.dataset.x = p[0];
        drawn.group.dataset.y = p[1];
        drawn.group.dataset.heading = heading.toFixed(1);
        drawn.label.setAttribute("x", p[0] + 12);
        drawn.label.setAttribute("y", Y(p[1]) - 10);
        drawn.label.textContent = `${vehicle.id} · ${fmt(p[2], 0)} m`;
      }
      const points = [...vehicle.track_m, ...(shown ? [p] : [])];
      drawn.track.setAttribute("points", points.map((q) => `${q[0]},${Y(q[1])}`).join(" "));
      const t = vehicle.target_m;
      drawn.target.style.display = t ? "" : "none";
      if (t) {
        drawn.target.setAttribute("transform", `translate(${t[0]} ${Y(t[1])})`);
        if (shown) {
          drawn.line.setAttribute("x1", p[0]);
          drawn.line.setAttribute("y1", Y(p[1]));
          drawn.line.setAttribute("x2", t[0]);
          drawn.line.setAttribute("y2", Y(t[1]));
        }
      } else {
        drawn.line.style.display = "none";
      }
    });
    for (const [id, drawn] of vehicles) {
      if (!seen.has(id)) {
        for (const node of Object.values(drawn)) node.remove();
        vehicles.delete(id);
      }
    }
  }

  // ------------------------------------------------------------------ the side panel

  function fact(dl, name, value, attrs = {}) {
    const dt = document.createElement("dt");
    dt.textContent = name;
    const dd = document.createElement("dd");
    dd.textContent = value;
    for (const [k, v] of Object.entries(attrs)) dd.dataset[k] = v;
    dl.append(dt, dd);
    return dd;
  }

  const point = (p) => (p ? `(${fmt(p[0], 0)}, ${fmt(p[1], 0)}, ${fmt(p[2], 0)}) m` : "–");

  function renderVehicleCards(list) {
    const cards = [];
    for (const vehicle of list) {
      const card = document.createElement("section");
      card.className = "card";
      card.dataset.vehicleId = vehicle.id;
      const h2 = document.createElement("h2");
      h2.textContent = vehicle.id;
      const link = document.createElement("span");
      link.className = "badge";
      link.dataset.testid = `link-${vehicle.id}`;
      const word = LINK_WORDS[vehicle.link] || vehicle.link;
      link.dataset.state = word;
      link.textContent = `link ${word}`;
      h2.append(link);
      const dl = document.createElement("dl");
      fact(dl, "mode", `${vehicle.mode || "–"}${vehicle.armed ? ", armed" : ", disarmed"}`);
      fact(dl, "streaming", vehicle.streaming ? "yes" : "no");
      const control = vehicle.control || { holder: "service", reason: "" };
      fact(dl, "control", control.holder === "service" ? "service" : `${control.holder}: ${control.reason}`, {
        testid: `control-${vehicle.id}`,
        holder: control.holder,
      });
      fact(dl, "position", point(vehicle.position_m));
      fact(dl, "heading", vehicle.heading_deg === null ? "from track" : `${fmt(vehicle.heading_deg, 0)}°`);
      fact(dl, "target", point(vehicle.target_m));
      const decision = vehicle.decision;
      if (decision && decision.age_s !== null) {
        fact(dl, "last decision", "", { ageBase: decision.age_s, suffix: ` ago (${decision.source})` });
      } else {
        fact(dl, "last decision", "none yet");
      }
      fact(dl, "heartbeat", vehicle.heartbeat_age_s === null ? "never" : `${fmt(vehicle.heartbeat_age_s, 1)} s ago`);
      card.append(h2, dl);
      cards.push(card);
    }
    $("vehicles").replaceChildren(...cards);
  }

  function renderUtility(utility, history) {
    for (const part of ["value", "throughput", "delay", "loss"]) {
      $(`utility-${part}`).textContent = utility ? fmt(utility[part], 3) : "–";
    }
    const chart = $("chart");
    chart.replaceChildren();
    for (const v of [0.25, 0.5, 0.75]) {
      el("line", { x1: 0, x2: 300, y1: 150 * (1 - v), y2: 150 * (1 - v), class: "chart-grid" }, chart);
    }
    if (!history.length) return;
    const tEnd = history[history.length - 1][0];
    const spanS = clamp(tEnd - history[0][0], 30, CHART_SPAN_S); // what there is, up to 5 min
    const tStart = tEnd - spanS;
    const shown = history.filter((h) => h[0] >= tStart);
    const series = ["value", "throughput", "delay", "loss"];
    series.forEach((name, i) => {
      const points = shown
        .map((h) => `${(((h[0] - tStart) / spanS) * 300).toFixed(1)},${(150 * (1 - h[i + 1])).toFixed(1)}`)
        .join(" ");
      el("polyline", { points, class: `series s-${name}` }, chart);
    });
    $("chart-note").textContent =
      `the last ${Math.round(spanS)} s (up to ${CHART_SPAN_S / 60} min), one point a report`;
  }

  function renderUsersTable(list, delayRef) {
    $("user-count").textContent = list.length;
    const rows = [...list]
      .sort((a, b) => b.offered_bps - a.offered_bps)
      .slice(0, TABLE_ROWS)
      .map((user) => {
        const tr = document.createElement("tr");
        const cells = [
          user.id,
          mbps(user.offered_bps),
          `${Math.round(100 * user.served)} %`,
          `${fmt(user.delay_s * 1000, 0)} ms`,
          `${fmt(100 * user.plr, 1)} %`,
        ];
        for (const text of cells) {
          const td = document.createElement("td");
          td.textContent = text;
          tr.append(td);
        }
        tr.firstChild.style.color = qualityColour(quality(user, delayRef));
        return tr;
      });
    $("users").tBodies[0].replaceChildren(...rows);
  }

  // Ages move on between frames: the frame's age plus the time since it arrived.
  function tick() {
    if (!view.frame) return;
    const elapsed = (performance.now() - view.receivedAt) / 1000;
    for (const dd of document.querySelectorAll("[data-age-base]")) {
      dd.textContent = `${fmt(Number(dd.dataset.ageBase) + elapsed, 1)} s${dd.dataset.suffix}`;
    }
    const report = view.frame.report;
    $("report-age").textContent = report
      ? `${fmt(report.age_s + elapsed, 1)} s ago${report.stale ? " (stale)" : ""}`
      : "none yet";
  }

  setInterval(tick, 250);
  run();
})();
