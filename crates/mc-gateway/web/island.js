// The island view (docs/web.md): draws the snapshot of api/island, then keeps it current from the
// server-sent events of api/events. Plain browser JavaScript, no library, no build step.
'use strict';
(() => {
  const SVG = 'http://www.w3.org/2000/svg';
  const R = 46;                 // circumradius of a static hexagon
  const CELL = 2 * R;           // grid hexagon: leaves room for mobile elements between statics
  const M = 0.42 * R;           // circumradius of a mobile hexagon
  const APO = Math.sqrt(3) / 2; // apothem per unit of circumradius
  const STALE_AFTER_MS = 3000;  // no word from the gateway for this long: say it is lost
  const REBOOT_SHOWN_MS = 30000;
  const TIMELINE_MAX = 300;
  const DARK = '#39414b';      // an element whose LEDs are off or not known

  const $ = (id) => document.getElementById(id);
  const S = {
    seq: 0, ready: false, queue: [], nodes: new Map(), layout: {}, controls: 'read_only',
    events: [], health: null, selected: null, results: new Map(), pending: new Map(),
    lastBeat: Date.now(), stale: false, es: null, loading: false,
    // A firmware update per element: { phase, percent } while it runs, then { outcome, reason };
    // and the last update's image (version, release notes).
    fw: new Map(), fwImage: null,
    // The retained leases and procedures documents, with when they were received (their
    // `remaining_ms` count from then).
    leases: [], procedures: [], workAt: Date.now(),
    token: localStorage.getItem('ihex-token') || '',
  };

  // ---- small DOM helpers ----
  function el(tag, attrs, ...kids) {
    const e = document.createElement(tag);
    for (const [k, v] of Object.entries(attrs || {})) {
      if (v !== undefined && v !== null) e.setAttribute(k, v);
    }
    for (const k of kids) e.append(k);
    return e;
  }
  function svg(tag, attrs, ...kids) {
    const e = document.createElementNS(SVG, tag);
    for (const [k, v] of Object.entries(attrs || {})) {
      if (v !== undefined && v !== null) e.setAttribute(k, v);
    }
    for (const k of kids) e.append(k);
    return e;
  }
  function fact(dl, name, value, id) {
    const dd = el('dd', id ? { id } : {});
    if (value instanceof Node) dd.append(value); else dd.textContent = value;
    dl.append(el('dt', {}, name), dd);
  }
  const yesNo = (b, yes, no) => el('span', { class: b ? 'yes' : 'no' }, b ? yes : no);
  const unknown = 'unknown';

  // ---- what an element is ----
  function ledOf(n) {
    const led = n.led;
    if (!led || led.mode === 'off' || !led.color) return { mode: led ? 'off' : 'unknown', color: null };
    return { mode: led.mode, color: led.color, period: led.period_ms || 500, duty: led.duty || 50 };
  }
  function lastReboot(id) {
    return S.events.find((e) => e.ev.event === 'node_rebooted' && e.ev.payload.id === id);
  }
  function statusOf(n) {
    if (!n.online) return 'lost';
    const r = lastReboot(n.id);
    if (r && Date.now() - r.time < REBOOT_SHOWN_MS) return 'rebooted';
    return 'online';
  }
  function ageMs(n) { return Math.max(0, Date.now() - n._seenAt); }
  function age(ms) {
    if (ms < 1000) return 'just now';
    const s = Math.round(ms / 1000);
    if (s < 90) return s + ' s ago';
    if (s < 5400) return Math.round(s / 60) + ' min ago';
    return Math.round(s / 3600) + ' h ago';
  }
  function firmwareOf(n) {
    if (n.firmware && typeof n.firmware === 'object') return n.firmware.version || unknown;
    return n.firmware || n.version || unknown;
  }
  function buzzerText(n) {
    if (!n.buzzer) return unknown;
    const b = n.buzzer;
    if (b.mode === 'on') return 'on ' + b.freq_hz + ' Hz';
    if (b.mode === 'pattern') return 'beeping ' + b.freq_hz + ' Hz';
    return b.mode;
  }
  function relayText(n) { return n.relay === null || n.relay === undefined ? unknown : (n.relay ? 'on' : 'off'); }
  // Its dockings as the gateway records them, and those of elements in its ports without power.
  function dockText(n) {
    const link = (port, peer, peerPort) => 'port ' + port + ' ↔ ' + peer + ' port ' + peerPort;
    const texts = (n.connections || []).map((c) => link(c.port, c.peer, c.peer_port));
    const unpowered = unpoweredDocks();
    const u = unpowered.byMobile.get(n.id);
    if (u) texts.push(link(u.ownPort, u.static, u.port) + ', no power');
    for (const c of unpowered.byPort.values()) {
      if (c.static === n.id) texts.push(link(c.port, c.peer, c.peer_port) + ', no power');
    }
    if (texts.length) return texts.join(', ');
    return n.role === 'mobile' ? 'free' : '–';
  }
  function loopsText(n) {
    const loops = n.loops || [];
    if (!loops.length) return 'none';
    return (loops.length === 1 ? 'port ' : 'ports ') + loops.join(', ');
  }

  // Where a mobile element was last docked, from the newest docking event naming it.
  function lastDock(id) {
    const e = S.events.find((x) => (x.ev.event === 'new_connection' || x.ev.event === 'connection_removed')
      && x.ev.payload && x.ev.payload.n && x.ev.payload.n.id === id);
    if (!e) return null;
    const p = e.ev.payload;
    return { static: p['n-1'].id, port: p['n-1'].port, ownPort: p.n.port };
  }
  // Mobile elements that lost their power while still in a port: the gateway ends their connection
  // when they go silent, but the static element's signal loop on that port is still closed and no
  // other element is recorded there, so they are physically docked, only unpowered.
  function unpoweredDocks() {
    const byMobile = new Map(), byPort = new Map();
    for (const m of S.nodes.values()) {
      if (m.role !== 'mobile' || m.online || (m.connections && m.connections.length)) continue;
      const d = lastDock(m.id);
      const s = d && S.nodes.get(d.static);
      if (!s || s.role !== 'static' || !(s.loops || []).includes(d.port)) continue;
      if ((s.connections || []).some((c) => c.port === d.port)) continue;
      const key = d.static + ':' + d.port;
      if (byPort.has(key)) continue;
      byMobile.set(m.id, d);
      byPort.set(key, { static: d.static, port: d.port, peer: m.id, peer_port: d.ownPort, unpowered: true });
    }
    return { byMobile, byPort };
  }

  // ---- geometry ----
  function axialToPixel(q, r) { return [CELL * 1.5 * q, CELL * Math.sqrt(3) * (r + q / 2)]; }
  // Axial directions, clockwise from lower right: the automatic arrangement fills rings around the
  // first element in this order.
  const DIRS = [[1, 0], [0, 1], [-1, 1], [-1, 0], [0, -1], [1, -1]];
  function* spiral() {
    yield [0, 0];
    for (let k = 1; ; k++) {
      let q = DIRS[0][0] * k, r = DIRS[0][1] * k;
      for (let side = 2; side < 8; side++) {
        for (let i = 0; i < k; i++) {
          yield [q, r];
          q += DIRS[side % 6][0]; r += DIRS[side % 6][1];
        }
      }
    }
  }
  // Outward normal of port p: port 0 is the top side, then clockwise (screen y points down).
  function portAngle(p) {
    const rad = (-90 + 60 * p) * Math.PI / 180;
    return p < 6 ? rad : (-60 + 120 * (p - 6)) * Math.PI / 180; // ports 6, 7: right-hand corners
  }
  function hexPoints(cx, cy, rad) {
    const pts = [];
    for (let i = 0; i < 6; i++) {
      const a = i * Math.PI / 3;
      pts.push((cx + rad * Math.cos(a)).toFixed(1) + ',' + (cy + rad * Math.sin(a)).toFixed(1));
    }
    return pts.join(' ');
  }
  function compareIds(a, b) { return parseInt(a, 16) - parseInt(b, 16); }

  // Static elements: configured positions first, the rest spiral around them in ID order.
  function placeStatics(statics) {
    const pos = new Map();
    const taken = new Set();
    for (const n of statics) {
      const h = S.layout[n.id];
      if (h) { pos.set(n.id, [h.q, h.r]); taken.add(h.q + ',' + h.r); }
    }
    const it = spiral();
    for (const n of statics) {
      if (pos.has(n.id)) continue;
      let c;
      do { c = it.next().value; } while (taken.has(c[0] + ',' + c[1]));
      taken.add(c[0] + ',' + c[1]);
      pos.set(n.id, c);
    }
    return pos;
  }

  // ---- the map ----
  function elementGroup(id, n, cx, cy, rad, role) {
    const led = n ? ledOf(n) : { mode: 'unknown', color: null };
    const status = n ? statusOf(n) : 'unknown';
    const g = svg('g', {
      class: 'element ' + status + (S.selected === id ? ' selected' : '') + (procedureTargets().has(id) ? ' target' : ''),
      'data-node': id, 'data-role': role, 'data-status': status,
      'data-led': led.color || 'off', 'data-led-mode': led.mode,
      'data-relay': n ? relayText(n) : unknown, 'data-buzzer': n && n.buzzer ? n.buzzer.mode : unknown,
      tabindex: 0, role: 'button', 'aria-label': 'element ' + id,
    });
    const body = svg('polygon', { class: 'body', points: hexPoints(cx, cy, rad), fill: led.color || DARK });
    g.append(body);
    if (led.mode === 'blink' && body.animate) {
      const d = Math.min(0.99, Math.max(0.01, led.duty / 100));
      body.animate([
        { fillOpacity: 1, offset: 0 }, { fillOpacity: 1, offset: d },
        { fillOpacity: 0.12, offset: d }, { fillOpacity: 0.12, offset: 1 }],
      { duration: led.period, iterations: Infinity });
    }
    g.append(svg('text', { class: 'id', x: cx, y: cy - (role === 'static' ? 8 : 0),
      'font-size': role === 'static' ? 18 : 13 }, id));
    g.append(svg('title', {}, 'element ' + id + ' (' + role + '): ' + status + ', LED ' + (led.color || led.mode)));
    if (role === 'static' && n) {
      // Inside the ring of ports: the status under the ID, the relay and buzzer signs in the left and
      // right corners, where no port and no port number is.
      const inset = R - 12;
      if (status !== 'online') {
        g.append(svg('text', { class: 'tag status', x: cx, y: cy + 9 }, status === 'rebooted' ? 'reboot' : status));
      }
      if (n.relay) g.append(svg('text', { class: 'tag relay', x: cx + inset, y: cy }, '⚡'));
      if (n.buzzer && n.buzzer.mode !== 'off') g.append(svg('text', { class: 'tag buzzer', x: cx - inset, y: cy }, '♪'));
    } else if (n && n.buzzer && n.buzzer.mode !== 'off') {
      g.append(svg('text', { class: 'tag', x: cx, y: cy + 12 }, '♪'));
    }
    const fw = S.fw.get(id);
    if (fw) {
      // A running update: a bar under the ID filling with the transfer, the percent and phase in
      // its tooltip; at the end, the outcome.
      g.setAttribute('data-fw-phase', fw.outcome ? 'done' : fw.phase);
      if (!fw.outcome) g.setAttribute('data-fw-percent', fw.percent);
      if (fw.outcome) g.setAttribute('data-fw-outcome', fw.outcome);
      // On a static hexagon between the status word and port 3, inside ports 2 and 4.
      const w = role === 'static' ? 34 : rad * 1.1, top = cy + (role === 'static' ? 17 : rad * 0.55);
      const bar = svg('g', { class: 'fw' + (fw.outcome ? ' ' + fw.outcome : '') });
      bar.append(svg('rect', { class: 'fw-track', x: cx - w / 2, y: top, width: w, height: 5, rx: 2 }));
      const done = fw.outcome ? 1 : Math.min(1, fw.percent / 100);
      bar.append(svg('rect', { class: 'fw-fill', x: cx - w / 2, y: top, width: (w * done).toFixed(1), height: 5, rx: 2 }));
      bar.append(svg('title', {}, fw.outcome ? 'firmware update: ' + fw.outcome + (fw.reason ? ' (' + fw.reason + ')' : '')
        : 'firmware update: ' + fw.phase + ' ' + fw.percent + ' %'));
      g.append(bar);
    }
    g.addEventListener('click', () => select(id));
    g.addEventListener('keydown', (e) => { if (e.key === 'Enter' || e.key === ' ') select(id); });
    return g;
  }

  function renderMap() {
    const map = $('map');
    map.replaceChildren();
    const nodes = [...S.nodes.values()].sort((a, b) => compareIds(a.id, b.id));
    const statics = nodes.filter((n) => n.role === 'static');
    const pos = placeStatics(statics);
    const docked = new Set();
    const unpowered = unpoweredDocks();
    const layer = { lines: svg('g'), statics: svg('g'), mobiles: svg('g') };
    let minX = Infinity, minY = Infinity, maxX = -Infinity, maxY = -Infinity;
    const grow = (x, y, rad) => {
      minX = Math.min(minX, x - rad); maxX = Math.max(maxX, x + rad);
      minY = Math.min(minY, y - rad); maxY = Math.max(maxY, y + rad);
    };
    for (const n of statics) {
      const [cx, cy] = axialToPixel(...pos.get(n.id));
      grow(cx, cy, R + 2 * M + 12);
      const g = elementGroup(n.id, n, cx, cy, R, 'static');
      g.setAttribute('data-hex', pos.get(n.id).join(','));
      const ports = n.ports === null || n.ports === undefined ? 6 : n.ports;
      const loops = new Set(n.loops || []);
      const onPort = new Map((n.connections || []).map((c) => [c.port, c]));
      for (let p = 0; p < ports; p++) {
        const u = unpowered.byPort.get(n.id + ':' + p);
        if (u) onPort.set(p, u);
      }
      for (let p = 0; p < ports; p++) {
        const a = portAngle(p);
        const d = R * APO - 9;
        const x = cx + d * Math.cos(a), y = cy + d * Math.sin(a);
        const closed = loops.has(p);
        const c = onPort.get(p);
        let what = ': free';
        if (c) what = ': element ' + c.peer + ' docked (by its port ' + c.peer_port + ')' + (c.unpowered ? ', without power' : '');
        else if (closed) what = ': signal loop closed, no element known on it yet';
        g.append(svg('circle', { class: 'port' + (closed ? ' closed' : ''), 'data-port': p, cx: x, cy: y, r: 7 },
          svg('title', {}, 'port ' + p + what)));
        g.append(svg('text', { class: 'port-no' + (closed ? ' closed' : ''), x, y }, p));
      }
      layer.statics.append(g);
      for (const c of onPort.values()) {
        const a = portAngle(c.port);
        const dist = R * APO + M * APO + 6;
        const mx = cx + dist * Math.cos(a), my = cy + dist * Math.sin(a);
        layer.lines.append(svg('line', { class: 'dock-line' + (c.unpowered ? ' unpowered' : ''), x1: cx + R * APO * Math.cos(a), y1: cy + R * APO * Math.sin(a),
          x2: mx - M * APO * Math.cos(a), y2: my - M * APO * Math.sin(a) }));
        const mg = elementGroup(c.peer, S.nodes.get(c.peer), mx, my, M, 'mobile');
        mg.setAttribute('data-docked-to', n.id);
        mg.setAttribute('data-dock-port', c.port);
        mg.setAttribute('data-own-port', c.peer_port);
        mg.setAttribute('data-power', c.unpowered ? 'off' : 'on');
        if (c.unpowered) mg.classList.add('unpowered');
        layer.mobiles.append(mg);
        docked.add(c.peer);
      }
    }
    if (minX === Infinity) { minX = -R; maxX = R; minY = -R; maxY = R; }
    // Elements on no static element's side: free mobiles, and nodes whose role is not known yet.
    // The tray's row is always there, so the map keeps its scale when an element comes or goes.
    const loose = nodes.filter((n) => n.role !== 'static' && !docked.has(n.id));
    const trayTop = maxY, trayY = maxY + M + 26;
    map.append(svg('text', { class: 'tray-title', x: minX, y: trayTop + 14 }, loose.length ? 'not docked' : 'not docked: none'));
    grow(minX + M + 4, trayY, M + 4);
    loose.forEach((n, i) => {
      const x = minX + M + 4 + i * (2 * M + 14);
      const g = elementGroup(n.id, n, x, trayY, M, n.role || 'unknown');
      g.setAttribute('data-free', 'true');
      layer.mobiles.append(g);
      grow(x, trayY, M + 4);
    });
    map.append(layer.lines, layer.statics, layer.mobiles);
    const pad = 8;
    map.setAttribute('viewBox', [minX - pad, minY - pad, maxX - minX + 2 * pad, maxY - minY + 2 * pad].map((v) => v.toFixed(1)).join(' '));
  }

  // ---- the elements table ----
  function renderTable() {
    const body = $('elements').tBodies[0];
    body.replaceChildren();
    for (const n of [...S.nodes.values()].sort((a, b) => compareIds(a.id, b.id))) {
      const status = statusOf(n);
      const led = ledOf(n);
      const ledCell = el('td', { class: 'led' });
      if (led.color) ledCell.append(el('span', { class: 'swatch', 'data-color': led.color }));
      ledCell.append(led.color ? led.mode + ' ' + led.color : led.mode);
      const sw = ledCell.querySelector('.swatch');
      if (sw) sw.style.background = led.color;
      const res = S.results.get(n.id);
      const tr = el('tr', { 'data-node': n.id, 'data-status': status, class: S.selected === n.id ? 'selected' : null },
        el('td', {}, n.id), el('td', {}, n.role || unknown),
        el('td', {}, el('span', { class: 'badge ' + status }, status)),
        el('td', { class: 'age', 'data-node': n.id }, age(ageMs(n))),
        ledCell, el('td', {}, buzzerText(n)), el('td', {}, relayText(n)), el('td', {}, dockText(n)),
        el('td', {}, firmwareOf(n)), el('td', { class: 'uid' }, n.uid || unknown),
        el('td', { class: 'result' }, res ? res.text : ''));
      tr.addEventListener('click', () => select(n.id));
      body.append(tr);
    }
    const filter = $('timeline-filter');
    const chosen = filter.value;
    filter.replaceChildren(el('option', { value: '' }, 'all'));
    for (const id of [...S.nodes.keys()].sort(compareIds)) filter.append(el('option', { value: id }, id));
    filter.value = S.nodes.has(chosen) ? chosen : '';
  }

  function renderAges() {
    for (const td of document.querySelectorAll('td.age')) {
      const n = S.nodes.get(td.dataset.node);
      if (n) td.textContent = age(ageMs(n));
    }
    const seen = $('detail-seen');
    if (seen && S.selected && S.nodes.has(S.selected)) seen.textContent = age(ageMs(S.nodes.get(S.selected)));
  }

  // ---- the selected element ----
  function select(id) {
    S.selected = id;
    render();
  }

  function renderDetails() {
    const id = S.selected;
    const n = id ? S.nodes.get(id) : null;
    $('details-empty').hidden = !!n;
    $('details-body').hidden = !n;
    if (!n) return;
    $('details-body').dataset.node = id;
    const status = statusOf(n);
    $('details-title').textContent = 'Element ' + id + ' (' + (n.role || 'role unknown') + ')';
    const dl = $('details-facts');
    dl.replaceChildren();
    fact(dl, 'State', el('span', { class: 'badge ' + status }, status));
    fact(dl, 'Last seen', age(ageMs(n)), 'detail-seen');
    const led = ledOf(n);
    fact(dl, 'LED', led.color ? led.mode + ' ' + led.color + (led.mode === 'blink' ? ' (' + led.period + ' ms, ' + led.duty + ' %)' : '') : led.mode);
    fact(dl, 'Buzzer', buzzerText(n));
    fact(dl, 'Relay', relayText(n));
    fact(dl, 'Docking', dockText(n));
    if (n.role !== 'mobile') fact(dl, 'Closed signal loops', loopsText(n));
    fact(dl, 'Firmware', firmwareOf(n));
    const fw = S.fw.get(id);
    if (fw) {
      fact(dl, 'Update', fw.outcome ? fw.outcome + (fw.reason ? ' (' + fw.reason + ')' : '') : fw.phase + ', ' + fw.percent + ' %', 'detail-fw');
    }
    if (fw && S.fwImage && S.fwImage.notes) fact(dl, 'Release notes', el('pre', { class: 'notes' }, S.fwImage.notes));
    fact(dl, 'UID', n.uid || unknown);
    const r = lastReboot(id);
    if (r) fact(dl, 'Last reboot', r.ev.payload.reset + ', ' + age(Date.now() - r.time));
    if (n.reported) fact(dl, 'CAN errors', 'TEC ' + n.reported.tec + ', REC ' + n.reported.rec + (n.reported.error_passive ? ' (error-passive)' : ''));
    const res = S.results.get(id);
    const out = $('details-result');
    out.textContent = res ? res.text : '';
    out.className = 'result ' + (res ? res.kind : '');
    renderControls(n);
  }

  function renderControls(n) {
    const note = $('controls-note');
    const readOnly = S.controls === 'read_only';
    note.hidden = !readOnly;
    note.textContent = readOnly ? 'Read-only: this gateway serves its view on the network without a token (--http-token), so its controls are off.' : '';
    $('token-form').hidden = !(S.controls === 'token' && !S.token);
    for (const f of document.querySelectorAll('#controls fieldset')) f.disabled = readOnly;
    $('relay-controls').disabled = readOnly || n.role === 'mobile';
  }

  // ---- health ----
  function renderHealth() {
    const h = S.health;
    const g = $('gateway-health'), b = $('bus-health');
    g.replaceChildren(); b.replaceChildren();
    if (!h) return;
    const gw = h.gateway, bus = h.bus;
    fact(g, 'MQTT', yesNo(gw.mqtt_connected, 'connected', 'disconnected'), 'mqtt-state');
    fact(g, 'Reconnects', gw.mqtt_reconnects, 'mqtt-reconnects');
    const up = gw.uptime_s;
    fact(g, 'Uptime', Math.floor(up / 3600) + ' h ' + Math.floor(up / 60) % 60 + ' min ' + up % 60 + ' s', 'uptime');
    const c = gw.commands;
    fact(g, 'Commands in flight', c.in_flight, 'commands-in-flight');
    fact(g, 'Commands done', c.ok + ' ok, ' + c.refused + ' refused, ' + c.timeout + ' timeout, ' + c.failed + ' failed, ' + c.rejected + ' rejected');
    fact(g, 'Version', gw.version);
    fact(b, 'Link', bus.link);
    fact(b, 'State', yesNo(!bus.bus_down, 'up', 'bus-off or interface down'), 'bus-state');
    fact(b, 'Frames/s', bus.frames_per_s.toFixed(1), 'bus-fps');
    fact(b, 'Load', bus.load_percent.toFixed(2) + ' % of ' + bus.bitrate / 1000 + ' kbit/s', 'bus-load');
    fact(b, 'Error frames', bus.error_frames, 'bus-error-frames');
    fact(b, 'Bus-off', bus.bus_off);
    fact(b, 'Interface down', bus.interface_down);
    fact(b, 'Receive drops', bus.rx_dropped);
    fact(b, 'Undecodable', bus.undecodable_frames);
    fact(b, 'Send failures', bus.send_failures);
    fact(b, 'Node faults', bus.faults);
  }

  // ---- the timeline ----
  function nodesOf(ev) {
    const p = ev.payload || {};
    const ids = [];
    for (const v of [p.id, p.node, p.n && p.n.id, p['n-1'] && p['n-1'].id]) if (typeof v === 'string' && v !== 'all') ids.push(v);
    for (const list of [p.acked, p.missing]) if (Array.isArray(list)) ids.push(...list);
    return [...new Set(ids)];
  }
  // Where a command came from (`origin` on command_result / command_rejected): the interface, the
  // identity something vouches for, and a name the sender only claimed, marked as such.
  function originText(o) {
    if (!o || typeof o !== 'object') return '';
    return ' · via ' + o.interface + (o.user ? ' by ' + o.user : '') + (o.claimed ? ', claimed ' + o.claimed : '');
  }
  function summary(ev) {
    const p = ev.payload || {};
    switch (ev.event) {
      case 'new_connection': return p.n.id + ' docked on ' + p['n-1'].id + ' port ' + p['n-1'].port + ' (by its port ' + p.n.port + ')';
      case 'connection_removed': return p.n.id + ' undocked from ' + p['n-1'].id + ' port ' + p['n-1'].port;
      case 'node_online': return p.id + (p.first_seen ? ' online' : ' back online') + (p.role ? ' (' + p.role + ')' : '');
      case 'node_lost': return p.id + ' lost: ' + p.missed + ' health checks missed';
      case 'node_rebooted': return p.id + ' rebooted (' + p.reset + '), version ' + p.version;
      case 'command_result': return p.cmd + ' → ' + p.node + ': ' + p.result + (p.reason ? ' (' + p.reason + ')' : '') + originText(p.origin);
      case 'command_rejected': return 'rejected: ' + p.reason + originText(p.origin);
      case 'fault': return p.node + ': ' + p.message;
      case 'bus_error': return p.message;
      case 'dock_failed': return 'docking on ' + p.node + ' port ' + p.port + ' failed: ' + p.reason;
      case 'node_list': return (p.nodes || []).length + ' nodes';
      case 'sim_result': return 'simulator ' + p.sim + ': ' + p.result + (p.reason ? ' (' + p.reason + ')' : '');
      case 'sim_rejected': return 'simulator: ' + p.reason;
      case 'fw_report': {
        const tally = {};
        for (const n of p.nodes || []) tally[n.outcome] = (tally[n.outcome] || 0) + 1;
        return 'firmware ' + p.version + ': ' + Object.entries(tally).map(([o, k]) => k + ' ' + o).join(', ');
      }
      case 'fw_correction': return p.node + ' ' + p.outcome + ' (was ' + p.was + '): ' + p.reason;
      case 'fw_upload': return 'image ' + p.name + ': ' + p.result + (p.reason ? ' (' + p.reason + ')' : '');
      case 'lease_granted': return 'lease ' + p.lease.id + ' (' + p.cmd + ') to ' + p.lease.owner;
      case 'lease_ended': return 'lease ' + p.lease.id + ' of ' + p.lease.owner + ' ' + p.why + (p.reason ? ' (' + p.reason + ')' : '');
      case 'procedure_started': return 'procedure ' + p.id + ' “' + p.name + '” started (' + p.steps + ' steps)';
      case 'procedure_step': return 'procedure ' + p.id + ' step ' + p.step + ' of ' + p.of + ': ' + p.state.replace('_', ' ') + (p.reason ? ' (' + p.reason + ')' : '');
      case 'procedure_mismatch': return 'procedure ' + p.id + ' step ' + p.step + ': ' + p.connection.n.id + ' ' + p.got + ' on ' + p.connection['n-1'].id + ' port ' + p.connection['n-1'].port + ', not what it waits for';
      case 'procedure_ended': return 'procedure ' + p.id + ' “' + p.name + '” ' + p.outcome.replace('_', ' ') + ' (' + p.steps_done + ' of ' + p.of + ' steps)' + (p.reason ? ': ' + p.reason : '');
      default: return JSON.stringify(p);
    }
  }
  const PROBLEMS = new Set(['node_lost', 'command_rejected', 'fault', 'bus_error', 'dock_failed', 'sim_rejected', 'procedure_mismatch']);
  const FW_PROBLEMS = new Set(['refused', 'reverted', 'unreachable', 'failed', 'lost_power']);
  function timelineItem(e) {
    const t = new Date(e.time);
    const hh = (v, n) => String(v).padStart(n || 2, '0');
    const when = hh(t.getHours()) + ':' + hh(t.getMinutes()) + ':' + hh(t.getSeconds()) + '.' + hh(t.getMilliseconds(), 3);
    const failed = (e.ev.event === 'command_result' && e.ev.payload.result !== 'ok')
      || (e.ev.event === 'fw_report' && (e.ev.payload.nodes || []).some((n) => FW_PROBLEMS.has(n.outcome)));
    return el('li', { 'data-event': e.ev.event, 'data-nodes': nodesOf(e.ev).join(' '),
      class: PROBLEMS.has(e.ev.event) || failed ? 'problem' : null },
    el('time', { datetime: t.toISOString() }, when), el('span', { class: 'name' }, e.ev.event),
    el('span', { class: 'what' }, summary(e.ev)));
  }
  function renderTimeline() {
    const list = $('timeline');
    const only = $('timeline-filter').value;
    list.replaceChildren(...S.events
      .filter((e) => !only || nodesOf(e.ev).includes(only))
      .map(timelineItem));
  }

  // ---- leases and procedures ----
  // The static elements the running procedures' current steps wait on: highlighted on the map.
  function procedureTargets() {
    return new Set(S.procedures.map((p) => p.wait.node));
  }

  function left(ms) {
    const s = Math.max(0, Math.ceil((ms - (Date.now() - S.workAt)) / 1000));
    return s >= 60 ? Math.floor(s / 60) + ' min ' + String(s % 60).padStart(2, '0') + ' s' : s + ' s';
  }

  function renderWork() {
    $('work-empty').hidden = S.leases.length + S.procedures.length > 0;
    $('procedures').replaceChildren(...S.procedures.map((p) => {
      const w = p.wait;
      const where = w.node + (w.port === null ? '' : ' port ' + w.port);
      const what = (w.mobile ? 'mobile ' + w.mobile : 'a mobile element') + ' ' + w.condition + ' on ' + where;
      const cancel = el('button', { type: 'button', class: 'cancel', 'data-procedure': p.id }, 'Cancel');
      cancel.disabled = S.controls === 'read_only' || (S.controls === 'token' && !S.token);
      cancel.addEventListener('click', () => cancelProcedure(p.id));
      return el('li', { class: 'procedure', 'data-procedure': p.id },
        el('strong', {}, 'Procedure ' + p.id + ' “' + p.name + '”'), ' — step ' + p.step + ' of ' + p.of,
        el('p', { class: 'step-text' }, p.text || what),
        el('p', { class: 'muted' }, 'waits for ' + what + '; ',
          el('span', { class: 'countdown', 'data-ms': p.remaining_ms }, left(p.remaining_ms)), ' left'),
        el('p', { class: 'result', id: 'procedure-result-' + p.id }, S.results.get('procedure ' + p.id) ? S.results.get('procedure ' + p.id).text : ''),
        cancel);
    }));
    $('leases').replaceChildren(...S.leases.map((l) => {
      const nodes = l.nodes === 'all' ? 'the island' : l.nodes.join(', ');
      const until = l.expires_at ? ' until ' + l.expires_at.slice(11, 19) + ' UTC' : '';
      return el('li', { class: 'lease', 'data-lease': l.id },
        el('strong', {}, nodes), ' leased by ', el('span', { class: 'owner' }, l.owner), until, ' (',
        el('span', { class: 'countdown', 'data-ms': l.remaining_ms }, left(l.remaining_ms)), ' left)',
        l.note ? el('p', { class: 'muted' }, 'note: ' + l.note) : '');
    }));
  }

  function renderCountdowns() {
    for (const c of document.querySelectorAll('#work .countdown')) c.textContent = left(Number(c.dataset.ms));
  }

  async function cancelProcedure(id) {
    const key = 'procedure ' + id;
    const request_id = 'web-' + Date.now().toString(36) + '-' + (++requests);
    S.pending.set(request_id, key);
    S.results.set(key, { text: 'cancel: sent…', kind: 'pending' });
    const headers = { 'Content-Type': 'application/json' };
    if (S.token) headers.Authorization = 'Bearer ' + S.token;
    try {
      const r = await fetch('api/command', { method: 'POST', headers,
        body: JSON.stringify({ cmd: 'procedure_cancel', id, request_id }) });
      if (!r.ok) {
        const body = await r.json().catch(() => ({}));
        S.pending.delete(request_id);
        S.results.set(key, { text: 'cancel: ' + (body.error || 'HTTP ' + r.status), kind: 'failed' });
      }
    } catch (err) {
      S.pending.delete(request_id);
      S.results.set(key, { text: 'cancel: not sent (' + (err.message || err) + ')', kind: 'failed' });
    }
    renderWork();
  }

  function render() {
    renderWork();
    renderMap();
    renderTable();
    renderDetails();
    renderTimeline();
    renderHealth();
  }

  // ---- applying what the gateway says ----
  function setNode(doc, at) {
    doc._seenAt = at - doc.last_seen_ms;
    S.nodes.set(doc.id, doc);
  }

  // The last command of each element, whoever gave it (this page, MQTT, Home Assistant, a tool):
  // every command_result names its node; a command_rejected names none, so only this page's own
  // rejections (found by their request_id) are shown beside an element.
  function noteResult(ev) {
    const p = ev.payload || {};
    const mine = p.request_id && S.pending.has(p.request_id) ? S.pending.get(p.request_id) : null;
    if (mine !== null) S.pending.delete(p.request_id);
    if (ev.event === 'command_rejected') {
      if (mine !== null) S.results.set(mine, { text: 'rejected: ' + p.reason + originText(p.origin), kind: 'failed' });
      return;
    }
    if (ev.event === 'procedure_ended' && mine !== null) {
      S.results.set(mine, { text: 'procedure ' + p.id + ' ' + p.outcome, kind: 'ok' });
      return;
    }
    if (ev.event !== 'command_result') return;
    const said = (result, reason) => ({ text: p.cmd + ': ' + result + (reason ? ' (' + reason + ')' : '') + originText(p.origin),
      kind: result === 'ok' ? 'ok' : 'failed' });
    if (p.node && p.node !== 'all') {
      S.results.set(p.node, said(p.result, p.reason));
    } else {
      for (const id of p.acked || []) S.results.set(id, said('ok'));
      for (const id of p.refused || []) S.results.set(id, said('refused'));
      for (const id of p.missing || []) S.results.set(id, said('timeout'));
    }
  }

  // What a firmware event says of each element; progress goes to the map, not to the timeline.
  function noteFw(ev) {
    const p = ev.payload || {};
    if (ev.event === 'fw_progress') {
      const was = S.fw.get(p.node);
      if (!was || was.outcome) S.fwImage = null; // a new update
      S.fw.set(p.node, { phase: p.phase, percent: p.percent });
      return true;
    }
    if (ev.event === 'fw_report') {
      S.fwImage = { version: p.version, notes: p.notes || null };
      for (const n of p.nodes || []) S.fw.set(n.node, { outcome: n.outcome, reason: n.reason });
    }
    if (ev.event === 'fw_correction') S.fw.set(p.node, { outcome: p.outcome, reason: p.reason });
    return false;
  }

  function applyEvent(ev, time) {
    if (noteFw(ev)) return;
    S.events.unshift({ ev, time });
    if (S.events.length > TIMELINE_MAX) S.events.length = TIMELINE_MAX;
    noteResult(ev);
  }

  function applySnapshot(snap) {
    const now = Date.now();
    S.seq = snap.seq;
    S.layout = snap.layout || {};
    S.controls = snap.controls;
    S.nodes = new Map();
    for (const doc of snap.nodes) setNode(doc, now);
    S.fw = new Map();
    for (const e of snap.events.slice().reverse()) noteFw(e.event);
    S.events = snap.events.filter((e) => e.event.event !== 'fw_progress').map((e) => ({ ev: e.event, time: e.time_ms }));
    for (let i = S.events.length - 1; i >= 0; i--) noteResult(S.events[i].ev);
    S.health = { gateway: snap.gateway, bus: snap.bus };
    S.leases = (snap.leases || { leases: [] }).leases;
    S.procedures = (snap.procedures || { procedures: [] }).procedures;
    S.workAt = now;
    $('island-name').textContent = snap.island ? '“' + snap.island + '”' : '';
  }

  function handle(e) {
    const now = Date.now();
    if (e.type === 'event' || e.type === 'state') {
      const seq = Number(e.lastEventId);
      if (seq && seq <= S.seq) return; // already in the snapshot
      if (seq) S.seq = seq;
      const data = JSON.parse(e.data);
      if (e.type === 'event') {
        applyEvent(data, now);
      } else {
        setNode(data, now);
      }
      render();
    } else if (e.type === 'health') {
      const h = JSON.parse(e.data);
      S.health = h;
      if (h.last_seen_ms) {
        for (const [id, ms] of Object.entries(h.last_seen_ms)) {
          const n = S.nodes.get(id);
          if (n) n._seenAt = now - ms;
        }
      }
      renderHealth();
      renderAges();
    } else if (e.type === 'leases' || e.type === 'procedures') {
      const seq = Number(e.lastEventId);
      if (seq && seq <= S.seq) return;
      if (seq) S.seq = seq;
      const doc = JSON.parse(e.data);
      // Both documents' countdowns run from the latest one received.
      S.leases.forEach((l) => { l.remaining_ms -= now - S.workAt; });
      S.procedures.forEach((p) => { p.remaining_ms -= now - S.workAt; });
      S.workAt = now;
      if (e.type === 'leases') S.leases = doc.leases; else S.procedures = doc.procedures;
      render();
    } else if (e.type === 'lagged') {
      loadSnapshot(); // publications were lost on the way: start again from a snapshot
    }
  }

  function onMessage(e) {
    S.lastBeat = Date.now();
    if (!S.ready) { S.queue.push(e); return; }
    handle(e);
  }

  // ---- the connection ----
  function setStale(why) {
    S.ready = false;
    if (!S.stale) {
      S.stale = true;
      document.body.classList.add('is-stale');
    }
    $('stale-why').textContent = why;
    $('stale').hidden = false;
    $('connection').textContent = 'not connected';
  }

  function clearStale() {
    S.stale = false;
    document.body.classList.remove('is-stale');
    $('stale').hidden = true;
    $('connection').textContent = 'live';
  }

  async function loadSnapshot() {
    if (S.loading) return;
    S.loading = true;
    S.ready = false;
    try {
      const r = await fetch('api/island', { cache: 'no-store' });
      if (!r.ok) throw new Error('api/island answered ' + r.status);
      const snap = await r.json();
      applySnapshot(snap);
      S.ready = true;
      const queued = S.queue;
      S.queue = [];
      for (const e of queued) handle(e);
      S.lastBeat = Date.now();
      clearStale();
      render();
    } catch (err) {
      setStale(String(err.message || err));
      setTimeout(() => { if (!S.ready && S.es && S.es.readyState === EventSource.OPEN) loadSnapshot(); }, 1000);
    } finally {
      S.loading = false;
    }
  }

  function connect() {
    if (S.es) S.es.close();
    S.ready = false;
    S.queue = [];
    const es = new EventSource('api/events');
    S.es = es;
    es.addEventListener('open', () => { S.lastBeat = Date.now(); loadSnapshot(); });
    es.addEventListener('error', () => {
      setStale('the connection closed');
      // The browser retries by itself unless the stream was refused outright.
      if (es.readyState === EventSource.CLOSED) setTimeout(connect, 1000);
    });
    for (const t of ['hello', 'event', 'state', 'leases', 'procedures', 'health', 'lagged']) es.addEventListener(t, onMessage);
  }

  // A gateway that vanishes without closing the connection (a cable pulled) only goes quiet.
  setInterval(() => {
    if (Date.now() - S.lastBeat > STALE_AFTER_MS && !S.stale) {
      setStale('no word from the gateway for ' + STALE_AFTER_MS / 1000 + ' s');
      connect();
    }
    if (!S.stale) { renderAges(); renderCountdowns(); }
  }, 500);

  // ---- controls ----
  let requests = 0;
  async function send(cmd) {
    const id = S.selected;
    if (!id) return;
    cmd.node = id;
    cmd.request_id = 'web-' + Date.now().toString(36) + '-' + (++requests);
    S.pending.set(cmd.request_id, id);
    S.results.set(id, { text: cmd.cmd + ': sent…', kind: 'pending' });
    renderDetails();
    const headers = { 'Content-Type': 'application/json' };
    if (S.token) headers.Authorization = 'Bearer ' + S.token;
    let text = null;
    try {
      const r = await fetch('api/command', { method: 'POST', headers, body: JSON.stringify(cmd) });
      if (r.status === 401) {
        S.token = '';
        localStorage.removeItem('ihex-token');
        S.controls = 'token';
      }
      if (!r.ok) {
        const body = await r.json().catch(() => ({}));
        text = cmd.cmd + ': ' + (body.error || 'HTTP ' + r.status);
      }
    } catch (err) {
      text = cmd.cmd + ': not sent (' + (err.message || err) + ')';
    }
    if (text !== null) {
      S.pending.delete(cmd.request_id);
      S.results.set(id, { text, kind: 'failed' });
    }
    renderDetails();
    renderTable();
  }
  const num = (id) => Number($(id).value);
  function wire() {
    $('led-set').addEventListener('click', () => {
      const cmd = { cmd: 'led', color: $('led-color').value, brightness: num('led-brightness') };
      if ($('led-blink').checked) cmd.blink = { period_ms: num('led-period'), duty: num('led-duty') };
      send(cmd);
    });
    $('led-off').addEventListener('click', () => send({ cmd: 'led', off: true }));
    $('buzzer-on').addEventListener('click', () => send({ cmd: 'buzzer', mode: 'on', freq_hz: num('buzzer-freq') }));
    $('buzzer-beep').addEventListener('click', () => send({ cmd: 'buzzer', mode: 'pattern', freq_hz: num('buzzer-freq'), on_ms: 150, off_ms: 150, count: 3 }));
    $('buzzer-off').addEventListener('click', () => send({ cmd: 'buzzer', mode: 'off' }));
    $('relay-on').addEventListener('click', () => send({ cmd: 'power', on: true }));
    $('relay-off').addEventListener('click', () => send({ cmd: 'power', on: false }));
    $('identify').addEventListener('click', () => send({ cmd: 'identify', seconds: num('identify-seconds') }));
    $('token-form').addEventListener('submit', (e) => {
      e.preventDefault();
      S.token = $('token').value.trim();
      localStorage.setItem('ihex-token', S.token);
      renderDetails();
    });
    $('timeline-filter').addEventListener('change', renderTimeline);
  }

  // ---- the audit trail's last records, with who sent each command (docs/audit.md) ----
  function auditWhat(r) {
    const d = r.data || {};
    switch (r.kind) {
      case 'command': return JSON.stringify(d.command !== undefined ? d.command : d);
      case 'answer': {
        const p = (d.payload || {});
        return d.event + (p.result ? ' ' + p.result : '') + (p.reason ? ': ' + p.reason : '');
      }
      case 'gap': return d.lost + ' records lost';
      default: return d.event || (r.kind === 'start' ? 'version ' + d.version : '');
    }
  }
  async function loadAudit() {
    try {
      const r = await fetch('api/audit', { cache: 'no-store' });
      const a = await r.json();
      $('audit-state').textContent = !a.on ? 'off on this gateway'
        : a.problem ? 'NOT RECORDING: ' + a.problem + ' (' + a.lost + ' records lost)'
        : a.written + ' records written since start';
      $('audit-state').className = a.problem ? 'problem' : 'muted';
      $('audit').tBodies[0].replaceChildren(...a.records.slice().reverse().map((r) =>
        el('tr', { 'data-kind': r.kind },
          el('td', {}, String(r.seq)), el('td', {}, r.ts.replace('T', ' ').replace('Z', '')),
          el('td', {}, r.kind), el('td', {}, r.interface || ''), el('td', { class: 'user' }, r.user || ''),
          el('td', {}, r.claimed ? r.claimed + ' (claimed)' : ''), el('td', {}, (r.elements || []).join(', ')),
          el('td', {}, auditWhat(r)))));
    } catch (e) {
      $('audit-state').textContent = 'not available (' + e.message + ')';
    }
  }

  wire();
  connect();
  loadAudit();
  setInterval(loadAudit, 2000);
})();
