// Shared by the dashboard's pages: the API key of this tab's session, JSON requests,
// the event stream (read with fetch so that a key can go with it), formatting.
"use strict";
const KEY = "inspection-api-key";

const desk = {
  key() { return sessionStorage.getItem(KEY) || ""; },
  headers(extra) {
    const h = Object.assign({}, extra || {});
    const k = desk.key();
    if (k) h["X-API-Key"] = k;
    return h;
  },
  async json(url, opts) {
    const o = Object.assign({}, opts || {});
    o.headers = desk.headers(o.headers);
    const r = await fetch(url, o);
    const body = await r.json().catch(() => null);
    if (!r.ok) throw new Error((body && body.error && body.error.message) || `HTTP ${r.status}`);
    return body;
  },
  post(url, body) {
    return desk.json(url, { method: "POST", body: JSON.stringify(body || {}),
                            headers: { "Content-Type": "application/json" } });
  },
  // Server-sent events over fetch; reconnects with Last-Event-ID so nothing is missed.
  // ``after``: the id of the newest result the page already shows (the stream starts after it).
  stream(url, handlers, after) {
    let last = after || null;
    const run = async () => {
      for (;;) {
        try {
          const h = desk.headers({ Accept: "text/event-stream" });
          if (last) h["Last-Event-ID"] = last;
          const r = await fetch(url, { headers: h });
          if (!r.ok) throw new Error(`HTTP ${r.status}`);
          const reader = r.body.getReader();
          const dec = new TextDecoder();
          let buf = "";
          for (;;) {
            const { value, done } = await reader.read();
            if (done) break;
            buf += dec.decode(value, { stream: true });
            let i;
            while ((i = buf.indexOf("\n\n")) >= 0) {
              const block = buf.slice(0, i); buf = buf.slice(i + 2);
              const ev = { event: "message", data: "", id: null };
              for (const line of block.split("\n")) {
                if (line.startsWith("event: ")) ev.event = line.slice(7);
                else if (line.startsWith("data: ")) ev.data += line.slice(6);
                else if (line.startsWith("id: ")) ev.id = line.slice(4);
              }
              if (ev.id) last = ev.id;
              const f = handlers[ev.event];
              if (f && ev.data) f(JSON.parse(ev.data));
            }
          }
        } catch (e) { if (handlers.error) handlers.error(e); }
        await new Promise((res) => setTimeout(res, 2000));  // the server went away: retry
      }
    };
    run();
  },
  time(ns) { return ns == null ? "" : new Date(ns / 1e6).toLocaleString(); },
  num(x, d) { return x == null ? "–" : Number(x).toFixed(d == null ? 3 : d); },
  esc(s) { return String(s == null ? "" : s).replace(/[&<>"']/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" }[c])); },
  badge(status) { return `<span class="badge ${desk.esc(status)}">${desk.esc(status)}</span>`; },
  // The comparison point farthest out of its band, as a share of the band's half-width.
  worst(r) {
    let best = null;
    for (const c of r.comparison || []) {
      if (c.deviation_mm == null) continue;
      const half = c.deviation_mm >= 0 ? Math.abs(c.upper_mm) : Math.abs(c.lower_mm);
      const ratio = half > 0 ? Math.abs(c.deviation_mm) / half : Infinity;
      if (!best || ratio > best.ratio) best = { c, ratio };
    }
    return best;
  },
  nav(here) {
    const links = [["/", "Board"], ["/ui/search", "Search"], ["/ui/trends", "Trends"], ["/docs", "API"]];
    const el = document.createElement("header");
    el.innerHTML = `<span class="brand">Inspection</span>` +
      links.map(([h, t]) => `<a href="${h}" class="${h === here ? "here" : ""}">${t}</a>`).join("") +
      `<span class="grow"></span><span class="who" id="who"></span>` +
      `<input id="key" type="password" placeholder="API key (for writes)" autocomplete="off">`;
    document.body.prepend(el);
    const input = el.querySelector("#key");
    const who = el.querySelector("#who");
    const show = () => { who.textContent = desk.key() ? "key set for this session" : ""; };
    input.addEventListener("change", () => { sessionStorage.setItem(KEY, input.value.trim()); input.value = ""; show(); });
    show();
  },
};
