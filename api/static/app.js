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
  // The chart's plot in its 300 x 150 viewBox: room on the left for the y-axis values.
  const CHART = { left: 26, right: 296, top: 6, bottom: 144 };
  const CHART_TICKS = [0, 0.25, 0.5, 0.75, 1];
  const GAP_PERIODS = 3; // no report for more than 3 report periods: the line breaks there
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
  let envelopesKey = null;
  let sitesKey = null;
  let H = 500;
  const Y = (y) => H - y; // north up
  const users = new Map(); // id -> {circle, title, label}
  const vehicles = new Map(); // id -> {group, body, label, track, target, line}

  function render(frame) {
    const key = JSON.stringify([frame.area, frame.geofence]);
    if (key !== areaKey) {
      areaKey = key;
      drawArea(frame.area, frame.geofence);
      clipUsers(frame.area);
    }
    const siteKey = JSON.stringify(frame.site || null);
    if (siteKey !== sitesKey) {
      sitesKey = siteKey;
      drawSite(frame.site || null);
    }
    drawCoverage(frame.vehicles.find((v) => v.coverage) || null);
    const envelopeKey = JSON.stringify(frame.envelopes || []);
    if (envelopeKey !== envelopesKey) {
      envelopesKey = envelopeKey;
      drawEnvelopes(frame.envelopes || []);
    }
    const delayRef = frame.utility ? frame.utility.delay_ref_s : 1;
    $("delay-ref").textContent = fmt(delayRef, 1);
    drawUsers(frame.users, delayRef);
    drawVehicles(frame.vehicles);
    $("policy").textContent = frame.policy.name;
    renderVehicleCards(frame.vehicles);
    renderUtility(frame.utility, frame.utility_history, frame.time_s);
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

  // The envelopes (sim/envelope): each inclusion's outline, and the no-fly volumes, hatched,
  // named with their heights; the legend line says the altitude band and the clearance.
  function drawEnvelopes(envelopes) {
    const layer = $("layer-envelope");
    layer.replaceChildren();
    const ring = (corners) => corners.map(([x, y]) => `${x},${Y(y)}`).join(" ");
    envelopes.forEach((envelope, index) => {
      const group = el("g", { class: "envelope" }, layer);
      group.dataset.envelope = index;
      el("polygon", { points: ring(envelope.inclusion), class: "inclusion" }, group);
      for (const zone of envelope.exclusions) {
        const shape = el("polygon", { points: ring(zone.polygon), class: "exclusion" }, group);
        shape.dataset.name = zone.name;
        const name = zone.name || "no-fly";
        const heights = `${fmt(zone.floor_m, 0)}–${fmt(zone.ceiling_m, 0)} m`;
        el("title", {}, shape).textContent = `${name}: no flight ${heights}`;
        const [cx, cy] = centroid(zone.polygon);
        const label = el("text", { x: cx, y: Y(cy), class: "exclusion-label" }, group);
        label.textContent = `${name} ≤${fmt(zone.ceiling_m, 0)} m`;
      }
    });
    const legend = $("envelope-legend");
    if (legend) {
      legend.textContent = envelopes
        .map(
          (e, i) =>
            `${envelopes.length > 1 ? `envelope ${i + 1}: ` : "envelope: "}altitude ` +
            `${fmt(e.floor_m, 0)}–${fmt(e.ceiling_m, 0)} m, clearance ${fmt(e.clearance_m, 0)} m, ` +
            `${e.exclusions.length} no-fly volume${e.exclusions.length === 1 ? "" : "s"}`,
        )
        .join(" · ");
    }
  }

  // A site (sim/sites): its buildings, the tallest in each square, grey by height.
  function drawSite(site) {
    const layer = $("layer-site");
    layer.replaceChildren();
    view.siteMaxHeight = 0;
    if (!site) return;
    const top = Math.max(1, ...site.heights_m);
    view.siteMaxHeight = top;
    site.heights_m.forEach((h, k) => {
      if (h <= 0) return;
      const i = k % site.nx;
      const j = Math.floor(k / site.nx);
      const shade = Math.round(200 - 140 * Math.min(h / top, 1));
      const cell = el(
        "rect",
        {
          x: i * site.cell_m,
          y: Y((j + 1) * site.cell_m),
          width: site.cell_m,
          height: site.cell_m,
          class: "building",
          fill: `rgb(${shade},${shade},${shade + 10})`,
          "fill-opacity": 0.85,
        },
        layer,
      );
      el("title", {}, cell).textContent = `building ${fmt(h, 0)} m`;
    });
  }

  // What the first vehicle with a coverage covers from where it is: path loss per square,
  // green (<= 90 dB) to red (>= 130 dB); a square with no path is left empty.
  function drawCoverage(vehicle) {
    const layer = $("layer-coverage");
    layer.replaceChildren();
    const legend = $("site-legend");
    if (!vehicle) {
      if (legend) legend.textContent = "";
      return;
    }
    const cov = vehicle.coverage;
    let covered = 0;
    cov.loss_db.forEach((loss, k) => {
      if (loss === null) return;
      covered += 1;
      const i = k % cov.nx;
      const j = Math.floor(k / cov.nx);
      const t = clamp((loss - 90) / 40, 0, 1);
      const hue = Math.round(120 * (1 - t));
      el(
        "rect",
        {
          x: i * cov.cell_m,
          y: Y((j + 1) * cov.cell_m),
          width: cov.cell_m,
          height: cov.cell_m,
          class: "coverage",
          fill: `hsl(${hue},70%,45%)`,
          "fill-opacity": 0.22,
        },
        layer,
      );
    });
    if (legend) {
      const share = Math.round((100 * covered) / Math.max(cov.loss_db.length, 1));
      legend.textContent =
        `Buildings grey (darker: taller, up to ${fmt(view.siteMaxHeight || 0, 0)} m); ` +
        `shaded: what ${vehicle.id} covers from where it is, green ≤ 90 dB path loss to red ` +
        `≥ 130 dB, ${share} % of the area has a path.`;
    }
  }

  const centroid = (corners) => {
    const n = corners.length || 1;
    return [
      corners.reduce((a, c) => a + c[0], 0) / n,
      corners.reduce((a, c) => a + c[1], 0) / n,
    ];
  };

  // Circle area proportional to the offered load: 4 m plus 4 m per sqrt(Mbit/s).
  const userRadius = (bps) => clamp(4 + 4 * Math.sqrt(Math.max(bps, 0) / 1e6), 4, 40);

  // How well a user is served, 0 (bad) to 1 (good): the worse of throughput/offered and
  // 1 - delay/delay_ref.
  const quality = (user, delayRef) =>
    clamp(Math.min(user.served, 1 - user.delay_s / delayRef), 0, 1);
  const qualityColour = (q) => `hsl(${Math.round(120 * q)} 70% 48%)`;

  // User circles are clipped to the area (a heavy user's circle, up to 40 m, would spill past
  // it); their labels go in a layer of their own above them, unclipped, placed inside the area.
  let areaW = 500;

  function clipUsers(area) {
    areaW = area.size_x_m;
    const map = $("map");
    let clip = $("users-clip");
    if (!clip) {
      const defs = el("defs", {});
      map.prepend(defs);
      clip = el("clipPath", { id: "users-clip" }, defs);
      el("rect", {}, clip);
      $("layer-users").setAttribute("clip-path", "url(#users-clip)");
      const labels = el("g", { id: "layer-user-labels" });
      $("layer-users").after(labels);
    }
    const rect = clip.firstChild;
    for (const [k, v] of Object.entries({ x: 0, y: 0, width: area.size_x_m, height: area.size_y_m })) {
      rect.setAttribute(k, v);
    }
  }

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
        const label = el("text", { class: "user-label" }, $("layer-user-labels") || layer);
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
      marker.label.textContent = labelled ? user.id : "";
    }
    for (const [id, marker] of users) {
      if (!seen.has(id)) {
        marker.circle.remove();
        marker.label.remove();
        users.delete(id);
      }
    }
    if (labelled) placeLabels(list);
  }

  // Each label beside its circle (right, left, above or below; moved inside the area where it
  // would leave it) where it overlaps no label placed before it, the heaviest users first. A
  // label with no such place is not shown (the circle's tooltip still names the user).
  function placeLabels(list) {
    const placed = [];
    const free = (b) =>
      placed.every((p) => b.x1 <= p.x0 || p.x1 <= b.x0 || b.y1 <= p.y0 || p.y1 <= b.y0);
    for (const user of [...list].sort((a, b) => b.offered_bps - a.offered_bps)) {
      const label = users.get(user.id).label;
      label.style.display = "";
      label.setAttribute("x", 0);
      label.setAttribute("y", 0);
      const box = label.getBBox(); // at (0, 0): the text's extent around its baseline start
      const r = userRadius(user.offered_bps);
      const cx = user.x_m;
      const cy = Y(user.y_m);
      const candidates = [
        [cx + r + 2, cy + 3], // right
        [cx - r - 2 - box.width, cy + 3], // left
        [cx - box.width / 2, cy - r - 2], // above
        [cx - box.width / 2, cy + r + 2 + box.height], // below
      ];
      const spot = candidates
        .map(([x, y]) => {
          const sx = clamp(x, 1 - box.x, areaW - 1 - box.x - box.width); // 1 m inside
          const sy = clamp(y, 1 - box.y, H - 1 - box.y - box.height);
          return { x: sx, y: sy, x0: sx + box.x, x1: sx + box.x + box.width,
            y0: sy + box.y, y1: sy + box.y + box.height };
        })
        .find(free);
      if (!spot) {
        label.style.display = "none";
        continue;
      }
      label.setAttribute("x", spot.x.toFixed(1));
      label.setAttribute("y", spot.y.toFixed(1));
      placed.push(spot);
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
        const route = el("polyline", { class: "route", stroke: colour }, targets);
        const target = el("g", { class: "target" }, targets);
        el("circle", { r: 7, class: "target-mark" }, target);
        el("line", { x1: -11, y1: 0, x2: 11, y2: 0, class: "target-mark" }, target);
        el("line", { x1: 0, y1: -11, x2: 0, y2: 11, class: "target-mark" }, target);
        const group = el("g", { class: "vehicle" }, $("layer-vehicles"));
        group.dataset.vehicleId = vehicle.id;
        const body = el("polygon", { points: "0,-11 8,9 0,4.5 -8,9", class: "vehicle-body" }, group);
        group.style.setProperty("--vehicle-colour", colour);
        const label = el("text", { class: "vehicle-label" }, $("layer-vehicles"));
        drawn = { group, body, label, track, target, line, route };
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
      // The route flown (its waypoints, the setpoint first) instead of a straight line to the
      // target where it bends; a holding vehicle shows none.
      const legs = vehicle.route && vehicle.route.kind !== "hold" ? vehicle.route.waypoints_m : [];
      const bends = shown && legs.length > 1;
      drawn.route.style.display = bends ? "" : "none";
      drawn.route.dataset.kind = vehicle.route ? vehicle.route.kind : "";
      if (bends) {
        drawn.route.setAttribute("points", [p, ...legs].map((q) => `${q[0]},${Y(q[1])}`).join(" "));
      }
      const t = vehicle.target_m;
      drawn.target.style.display = t ? "" : "none";
      if (t) {
        drawn.target.setAttribute("transform", `translate(${t[0]} ${Y(t[1])})`);
        drawn.line.style.display = shown && !bends ? "" : "none";
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
      const route = vehicle.route;
      if (route) {
        const words =
          route.kind === "hold"
            ? `holding: ${route.hold_reason}`
            : `${route.kind}, ${route.waypoints_m.length} waypoint${route.waypoints_m.length === 1 ? "" : "s"} left`;
        fact(dl, "route", words, { testid: `route-${vehicle.id}`, kind: route.kind });
      }
      const battery = vehicle.battery || {};
      if (battery.remaining_pct !== null && battery.remaining_pct !== undefined) {
        const home =
          battery.return_at_pct === null ? "" : ` · home at ${fmt(battery.return_at_pct, 0)} %`;
        fact(dl, "battery", `${fmt(battery.remaining_pct, 0)} %${home}`, {
          testid: `battery-${vehicle.id}`,
        });
      }
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

  // The utility and its parts against time, up to the frame's time (nowS): values on the y
  // axis; a line breaks where no report came for more than GAP_PERIODS report periods (the
  // median interval between the reports shown), and the gap is shaded and says how long.
  function renderUtility(utility, history, nowS) {
    for (const part of ["value", "throughput", "delay", "loss"]) {
      $(`utility-${part}`).textContent = utility ? fmt(utility[part], 3) : "–";
    }
    const chart = $("chart");
    chart.replaceChildren();
    const cy = (v) => CHART.top + (CHART.bottom - CHART.top) * (1 - v);
    for (const v of CHART_TICKS) {
      el("line", { x1: CHART.left, x2: CHART.right, y1: cy(v), y2: cy(v), class: "chart-grid" }, chart);
      const tick = el("text", { x: CHART.left - 4, y: cy(v) + 3, "text-anchor": "end", class: "chart-tick" }, chart);
      tick.textContent = String(v);
    }
    if (!history.length) return;
    const tEnd = Math.max(history[history.length - 1][0], nowS ?? -Infinity);
    const spanS = clamp(tEnd - history[0][0], 30, CHART_SPAN_S); // what there is, up to 5 min
    const tStart = tEnd - spanS;
    const shown = history.filter((h) => h[0] >= tStart);
    const cx = (t) => CHART.left + ((t - tStart) / spanS) * (CHART.right - CHART.left);
    const steps = shown.slice(1).map((h, k) => h[0] - shown[k][0]).sort((a, b) => a - b);
    const periodS = steps.length ? steps[Math.floor(steps.length / 2)] : 1;
    const gapS = GAP_PERIODS * Math.max(periodS, 1e-3);
    const runs = [[]];
    const gaps = [];
    shown.forEach((h, k) => {
      if (k > 0 && h[0] - shown[k - 1][0] > gapS) {
        gaps.push([shown[k - 1][0], h[0]]);
        runs.push([]);
      }
      runs[runs.length - 1].push(h);
    });
    const last = shown.length ? shown[shown.length - 1][0] : tStart;
    if (tEnd - last > gapS) gaps.push([last, tEnd]); // none since the last report
    for (const [t0, t1] of gaps) {
      const gap = el("rect", { x: cx(t0).toFixed(1), y: CHART.top, width: (cx(t1) - cx(t0)).toFixed(1),
        height: CHART.bottom - CHART.top, class: "chart-gap" }, chart);
      el("title", {}, gap).textContent = `no report for ${Math.round(t1 - t0)} s`;
    }
    const series = ["value", "throughput", "delay", "loss"];
    series.forEach((name, i) => {
      for (const run of runs) {
        const xy = run.map((h) => [cx(h[0]).toFixed(1), cy(h[i + 1]).toFixed(1)]);
        if (xy.length === 1) {
          el("circle", { cx: xy[0][0], cy: xy[0][1], r: 1.5, class: `series-dot s-${name}` }, chart);
        } else if (xy.length > 1) {
          el("polyline", { points: xy.map((q) => q.join(",")).join(" "), class: `series s-${name}` }, chart);
        }
      }
    });
    $("chart-note").textContent =
      `the last ${Math.round(spanS)} s (up to ${CHART_SPAN_S / 60} min), one point a report` +
      (gaps.length ? "; shaded: no report" : "");
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
