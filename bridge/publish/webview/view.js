// attitude-bridge live view: frames from the bridge's WebSocket, drawn with BokehJS.
// Read-only: the page never sends anything. window.attitudeView is what it shows (the
// browser tests read it).
"use strict";

const COLORS = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b",
                "#e377c2", "#7f7f7f", "#bcbd22", "#17becf"];
const REFERENCES = {
  vehicle: { name: "autopilot", color: "#000000", dash: "dashed", width: 2, alpha: 1.0 },
  truth: { name: "truth", color: "#888888", dash: "solid", width: 4, alpha: 0.6 },
};
const AXES = ["roll", "pitch", "yaw"];
//: The plots are redrawn at most this often (the indicators and numbers at every frame):
//: a redraw of the plots is most of what the page costs its machine.
const PLOT_PERIOD_MS = 250;

const view = { frames: 0, drawn: 0, hello: null, last: null, vehicles: {}, errors: [] };
window.attitudeView = view;

// BokehJS (about 1 MB) loads beside the live part, not before it: the indicators, the
// facts and the error table show with the first frame, the plots when BokehJS is ready.
// Scripts inserted with async = false run in the order they were inserted.
const bokehReady = new Promise((resolve, reject) => {
  const files = ["bokeh/bokeh.min.js", "bokeh/bokeh-api.min.js"];
  files.forEach((src, i) => {
    const script = document.createElement("script");
    script.src = src;
    script.async = false;
    script.onerror = () => reject(new Error(`${src} did not load`));
    if (i === files.length - 1) script.onload = () => resolve();
    document.head.append(script);
  });
});
bokehReady.catch((e) => view.errors.push(String(e)));

function fmt(x, digits = 1) {
  return x === null || x === undefined || Number.isNaN(x) ? "–" : Number(x).toFixed(digits);
}

function el(tag, attrs = {}, text = "") {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
  if (text) e.textContent = text;
  return e;
}

// --- attitude indicator: horizon by roll and pitch, heading written below ------------
function drawIndicator(canvas, att) {
  const ctx = canvas.getContext("2d");
  const w = canvas.width, h = canvas.height, r = w / 2;
  ctx.save();
  ctx.clearRect(0, 0, w, h);
  ctx.beginPath();
  ctx.arc(r, r, r - 1, 0, 2 * Math.PI);
  ctx.clip();
  if (!att) {
    ctx.fillStyle = "#ddd";
    ctx.fillRect(0, 0, w, h);
    ctx.restore();
    return;
  }
  const [, roll, pitch] = att;
  ctx.translate(r, r);
  ctx.rotate(-roll * Math.PI / 180);
  const shift = pitch * (r / 45);  // 45° of pitch moves the horizon by the radius
  ctx.fillStyle = "#6fa8dc";
  ctx.fillRect(-2 * w, -2 * h + shift, 4 * w, 2 * h);
  ctx.fillStyle = "#a0522d";
  ctx.fillRect(-2 * w, shift, 4 * w, 2 * h);
  ctx.strokeStyle = "#fff";
  ctx.lineWidth = 1.5;
  ctx.beginPath();
  ctx.moveTo(-w, shift);
  ctx.lineTo(w, shift);
  ctx.stroke();
  ctx.restore();
  ctx.strokeStyle = "#ff0";
  ctx.lineWidth = 3;
  ctx.beginPath();  // the aircraft, fixed
  ctx.moveTo(r - 0.55 * r, r);
  ctx.lineTo(r - 0.15 * r, r);
  ctx.lineTo(r, r + 0.12 * r);
  ctx.lineTo(r + 0.15 * r, r);
  ctx.lineTo(r + 0.55 * r, r);
  ctx.stroke();
}

// Fixed at load: a plot that follows the window's width is laid out again at every redraw.
function plotWidth() {
  return Math.max(600, Math.min(window.innerWidth - 80, 1400));
}

// The plots' legend, once, in HTML (a legend drawn in every plot at every redraw costs
// more than the lines).
function legend(series, primary) {
  const box = el("div", { class: "legend" });
  series.forEach((name, i) => {
    const ref = REFERENCES[name];
    const item = el("span", { class: "item" });
    const swatch = el("span", { class: "swatch" });
    swatch.style.borderTop = `${ref ? 3 : name === primary ? 4 : 2}px ${ref && ref.dash === "dashed" ? "dashed" : "solid"} ${ref ? ref.color : COLORS[i % COLORS.length]}`;
    item.append(swatch, document.createTextNode((ref ? ref.name : name) + (name === primary ? " ★" : "")));
    box.append(item);
  });
  return box;
}

// A buffer of points not yet plotted (plots not built, or not drawn for long: a hidden
// tab) keeps its last n: bounded whatever the page does.
function keepLast(buf, n) {
  if (buf.t.length > n) {
    for (const column of Object.values(buf)) column.splice(0, column.length - n);
  }
}

// --- one vehicle ----------------------------------------------------------------------
class VehicleView {
  constructor(sysid, v, windowS) {
    this.sysid = sysid;
    this.windowS = windowS;
    this.rollover = Math.ceil(windowS * (view.hello ? view.hello.frame_hz : 10)) + 5;
    this.series = [...v.labels, "vehicle", "truth"];
    this.primary = v.primary;
    this.lastT = {};
    const section = el("section", { class: "vehicle", "data-sysid": sysid });
    section.append(el("h2", { "data-field": "title" }, `Vehicle ${sysid}`));
    this.facts = el("div", { class: "facts" });
    for (const [key, label] of [["imu", "IMU"], ["input", "input"], ["dropped", "dropped"],
                                ["latency", "latency p50/p99"], ["flight", "flight state"],
                                ["aiding", "aiding"], ["declination", "declination"]]) {
      const span = el("span");
      span.append(el("b", {}, `${label}: `), el("span", { "data-field": key }, "–"));
      this.facts.append(span);
    }
    section.append(this.facts);
    this.indicators = {};
    const row = el("div", { class: "indicators" });
    for (const name of this.series) {
      const ref = REFERENCES[name];
      const box = el("div", { class: "indicator" + (name === v.primary ? " primary" : ""),
                              "data-series": name });
      box.append(el("div", { class: "name" },
                    (ref ? ref.name : name) + (name === v.primary ? " ★" : "")));
      const canvas = el("canvas", { width: 120, height: 120 });
      box.append(canvas, el("div", { class: "angles", "data-field": "angles" }, "–"));
      row.append(box);
      this.indicators[name] = { box, canvas, angles: box.querySelector(".angles") };
      drawIndicator(canvas, null);
    }
    section.append(row);
    this.table = el("table", { class: "errors" });
    section.append(this.table);
    section.append(legend(this.series, v.primary));
    const plots = el("div", { class: "plots" });
    section.append(plots);
    document.getElementById("vehicles").append(section);
    this.section = section;
    // Points wait here until the plots exist, and between plot redraws.
    this.buffer = {};
    for (const name of this.series) this.buffer[name] = { t: [], roll: [], pitch: [], yaw: [] };
    this.errorBuffer = {};
    for (const name of this.series.filter((n) => !REFERENCES[n] || n === "vehicle")) {
      this.errorBuffer[name] = { t: [], err: [] };
    }
    bokehReady.then(() => this.buildPlots(plots), () => {});
  }

  buildPlots(target) {
    const P = Bokeh.Plotting;
    const xRange = new Bokeh.DataRange1d({ follow: "end", follow_interval: this.windowS,
                                           range_padding: 0 });
    this.sources = {};
    this.errorSources = {};
    const figures = [];
    for (const axis of AXES) {
      const fig = P.figure({ height: 160, width: plotWidth(), x_range: xRange,
                             title: `${axis} [°]`, tools: "pan,xwheel_zoom,box_zoom,reset",
                             x_axis_label: axis === "yaw" ? "board time [s]" : null });
      figures.push(fig);
    }
    this.series.forEach((name, i) => {
      const src = new Bokeh.ColumnDataSource({ data: { t: [], roll: [], pitch: [], yaw: [] } });
      this.sources[name] = src;
      const ref = REFERENCES[name];
      const style = ref
        ? { line_color: ref.color, line_dash: ref.dash, line_width: ref.width,
            line_alpha: ref.alpha }
        : { line_color: COLORS[i % COLORS.length], line_width: name === this.primary ? 2.5 : 1.5 };
      AXES.forEach((axis, k) => {
        figures[k].line({ field: "t" }, { field: axis },
                        { source: src, ...style });
      });
    });
    // The error plot is shown on its own once there is a truth to be wrong against (a real
    // vehicle has none); its time axis follows the same window.
    const errRange = new Bokeh.DataRange1d({ follow: "end", follow_interval: this.windowS,
                                             range_padding: 0 });
    const errFig = P.figure({ height: 150, width: plotWidth(), x_range: errRange,
                              title: "error vs truth (total, RMS over the window) [°]",
                              tools: "pan,xwheel_zoom,box_zoom,reset" });
    this.series.filter((n) => !REFERENCES[n] || n === "vehicle").forEach((name, i) => {
      const src = new Bokeh.ColumnDataSource({ data: { t: [], err: [] } });
      this.errorSources[name] = src;
      const ref = REFERENCES[name];
      errFig.line({ field: "t" }, { field: "err" },
                  { source: src,
                    line_color: ref ? ref.color : COLORS[i % COLORS.length],
                    line_dash: ref ? ref.dash : "solid", line_width: 2 });
    });

    // shown with its first points (an empty plot has no range to start from)
    this.layout = P.gridplot(figures.map((f) => [f]), { toolbar_location: "right" });
    this.errFig = errFig;
    this.plotTarget = el("div");
    this.errTarget = el("div");
    target.append(this.plotTarget, this.errTarget);
  }

  // Take one frame: its points are kept for the plots, it is the one to draw next.
  // Drawing is separate (draw(), once per animation frame at most): a page that cannot
  // keep up draws less often, never falls behind.
  take(v, t) {
    const st = v.status || {};
    for (const name of this.series) {
      const att = v.series[name] || null;
      if (att && att[0] !== this.lastT[name]) {
        this.lastT[name] = att[0];
        const buf = this.buffer[name];
        buf.t.push(att[0]); buf.roll.push(att[1]); buf.pitch.push(att[2]); buf.yaw.push(att[3]);
        keepLast(buf, this.rollover);
      }
    }
    if (st.report_time !== this.lastReport) {
      this.lastReport = st.report_time;
      this.keepErrors(st, t);
      this.reportChanged = true;
    }
    this.latest = v;
  }

  draw() {
    const v = this.latest;
    if (!v) return;
    for (const name of this.series) {
      const att = v.series[name] || null;
      const ind = this.indicators[name];
      drawIndicator(ind.canvas, att);
      ind.angles.textContent = att
        ? `R ${fmt(att[1])}  P ${fmt(att[2])}  Y ${fmt(att[3])}` : "–";
    }
    const now = performance.now();
    if (!(now - this.lastFlush < PLOT_PERIOD_MS)) {
      this.lastFlush = now;
      this.flush();
    }
    if (this.reportChanged) {  // the facts change with each status report
      this.reportChanged = false;
      this.showFacts(v.status || {});
      this.showErrors(v.status || {});
    }
  }

  flush() {
    if (!this.sources) return;  // BokehJS still loading: the buffers hold the points
    for (const [name, buf] of Object.entries(this.buffer)) {
      if (buf.t.length) {
        this.sources[name].stream(buf, this.rollover);
        this.buffer[name] = { t: [], roll: [], pitch: [], yaw: [] };
      }
    }
    if (!this.plotsShown && this.sources[this.primary].data.t.length) {
      this.plotsShown = true;
      Bokeh.Plotting.show(this.layout, this.plotTarget)
        .catch((e) => view.errors.push(String(e)));
    }
    let errors = false;
    for (const [name, buf] of Object.entries(this.errorBuffer)) {
      if (buf.t.length) {
        this.errorSources[name].stream(buf, this.rollover);
        this.errorBuffer[name] = { t: [], err: [] };
        errors = true;
      }
    }
    if (errors && !this.errorsShown) {
      this.errorsShown = true;
      Bokeh.Plotting.show(this.errFig, this.errTarget)
        .catch((e) => view.errors.push(String(e)));
    }
  }

  keepErrors(st, t) {
    const truth = (st.compare || {}).truth;
    if (!truth || t === null || t === undefined) return;
    for (const [name, buf] of Object.entries(this.errorBuffer)) {
      const c = name === "vehicle" ? st.vehicle_vs_truth : truth[name];
      if (c && c.total_deg !== null && c.total_deg !== undefined) {
        buf.t.push(t);
        buf.err.push(c.total_deg);
        keepLast(buf, this.rollover);
      }
    }
  }

  showFacts(st) {
    const f = (key) => this.facts.querySelector(`[data-field="${key}"]`);
    const imu = st.imu || {};
    const title = this.section.querySelector('[data-field="title"]');
    title.textContent = `Vehicle ${this.sysid}` + (st.vehicle ? ` — ${st.vehicle}` : "") +
      (st.autopilot ? `, ${st.autopilot.replace("MAV_AUTOPILOT_", "")}` : "") +
      (st.online === false ? " (no data)" : "") + (st.initialising ? " (settling)" : "");
    f("imu").textContent = imu.message
      ? `${imu.message} ${fmt(imu.achieved_hz, 0)} Hz (asked ${fmt(imu.asked_hz, 0)}, ` +
        `${imu.state || "–"}) ±${fmt(imu.jitter_ms, 2)} ms` : "–";
    f("input").textContent = `${fmt(st.input_rate_hz, 0)} samples/s`;
    f("dropped").textContent = `${st.dropped ?? "–"} (lost in transit ${st.lost ?? "–"})`;
    const lat = st.latency_ms || {};
    f("latency").textContent = `${fmt(lat.p50, 2)} / ${fmt(lat.p99, 2)} ms`;
    const fs = st.flight_state || {};
    f("flight").textContent = `${fs.state || "–"} (${fs.source || "–"}` +
      (fs.armed === null || fs.armed === undefined ? "" : fs.armed ? ", armed" : ", disarmed") + ")";
    const aid = st.aiding || {};
    f("aiding").textContent = aid.enabled === false ? "off"
      : aid.source ? `${aid.source} (${aid.used ?? 0} used)` : "no velocity";
    const dec = st.declination || {};
    f("declination").textContent = dec.deg === undefined ? "–"
      : `${fmt(dec.deg, 2)}° (${dec.source}${dec.detail ? ": " + dec.detail : ""})`;
  }

  showErrors(st) {
    const compare = st.compare || {};
    const refs = Object.keys(compare);
    const rows = [["estimator", ...refs.flatMap((r) => [`vs ${r} total`, `vs ${r} incl.`])]];
    for (const label of this.series.filter((n) => !REFERENCES[n])) {
      rows.push([label + (label === this.primary ? " ★" : ""),
                 ...refs.flatMap((r) => {
                   const c = (compare[r] || {})[label] || {};
                   return [fmt(c.total_deg, 2), fmt(c.inclination_deg, 2)];
                 })]);
    }
    const own = st.vehicle_vs_truth;
    if (own) {
      rows.push(["autopilot", ...refs.flatMap((r) => r === "truth"
        ? [fmt(own.total_deg, 2), fmt(own.inclination_deg, 2)] : ["", ""])]);
    }
    this.table.replaceChildren(...rows.map((cells, i) => {
      const tr = el("tr", i ? { "data-row": cells[0].replace(" ★", "") } : {});
      cells.forEach((c) => tr.append(el(i ? "td" : "th", {}, c)));
      return tr;
    }));
  }
}

// --- the connection ---------------------------------------------------------------------
let drawScheduled = false;

function drawAll() {
  drawScheduled = false;
  for (const vv of Object.values(view.vehicles)) vv.draw();
  document.getElementById("frames").textContent = `frame ${view.frames}`;
  view.drawn += 1;
}

function apply(frame) {
  view.frames += 1;
  view.last = frame;
  const windowS = view.hello ? view.hello.window_s : 30;
  for (const [sysid, v] of Object.entries(frame.vehicles || {})) {
    if (!v.labels.length) continue;  // served, no estimate yet
    let vv = view.vehicles[sysid];
    if (!vv || vv.series.length !== v.labels.length + 2) {
      if (vv) vv.section.remove();
      vv = view.vehicles[sysid] = new VehicleView(sysid, v, windowS);
      const waiting = document.getElementById("waiting");
      if (waiting) waiting.remove();
    }
    vv.take(v, v.t);
  }
  if (!drawScheduled) {
    drawScheduled = true;
    requestAnimationFrame(drawAll);
  }
}

function connect() {
  const status = document.getElementById("connection");
  const ws = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws`);
  ws.onopen = () => { status.textContent = "live"; status.className = ""; };
  ws.onmessage = (event) => {
    const msg = JSON.parse(event.data);
    if (msg.type === "hello") {
      view.hello = msg;
      msg.history.forEach(apply);
    } else if (msg.type === "frame") {
      apply(msg);
    }
  };
  ws.onclose = (event) => {
    status.textContent = `disconnected${event.reason ? " (" + event.reason + ")" : ""}; retrying`;
    status.className = "down";
    setTimeout(connect, 2000);
  };
}

connect();
