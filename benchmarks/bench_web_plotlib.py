#!/usr/bin/env python3
"""Which plotting library the web view's page uses, by measurement: uPlot (vendored in
qradar/web/static/vendor/uplot) against Apache ECharts (``npm pack echarts@VERSION`` into a
temporary folder: this needs npm and the registry) on the page's own workload, in headless
chromium (tests/chromium.py).

The workload, the same for both, generated in the page: 3 sensors at 20 Hz each (a timer
per sensor, 50 ms apart, staggered), each frame a range profile of 2 receivers x 256 bins
and 2 targets with a 1-sigma ellipse, plus the last 12 frames' targets; drawn once per
animation frame, only what changed (as qradar/web/static/app.js does): a line plot per
sensor and one x-y scatter with the ellipses. Measured, per library, after ``--warmup`` s,
for ``--seconds``: the time to load the library (script evaluated), the frame time (the
page's work per animation frame, ``performance.now()``), the interval between animation
frames, and the browser's count of frames over 50 ms. Prints one JSON object.

    .venv/bin/python benchmarks/bench_web_plotlib.py [--echarts 6.1.0] [--seconds 10] [--warmup 2]
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import tarfile
import tempfile
import time
from pathlib import Path

import harness
from harness import ROOT, emit, machine

UPLOT = ROOT / "qradar" / "web" / "static" / "vendor" / "uplot"

#: the workload and its timing, shared by both pages; DRAW(state) is the library's part
COMMON = r"""
const N = 256, SENSORS = 3, TRAIL = 12, RING = 8192;
const perf = { frame: [], interval: [], long: 0, lastData: -1e9, pending: 0 };
const sensors = [...Array(SENSORS).keys()].map(i => ({ id: "s" + i, rx1: new Float64Array(N), rx2: new Float64Array(N),
  targets: [], trail: [], color: ["#1f77b4", "#d62728", "#2ca02c"][i] }));
const xs = Float64Array.from({ length: N }, (_, i) => i * 0.6);
const dirty = new Set(); let dirtyXY = false;
function tick(s) {
  const t0 = performance.now();
  for (let i = 0; i < N; i++) { s.rx1[i] = -40 + 8 * Math.random() + (i === 15 ? 30 : 0); s.rx2[i] = s.rx1[i] - 3 * Math.random(); }
  s.trail.push(s.targets); if (s.trail.length > TRAIL) s.trail.shift();
  s.targets = [0, 1].map(k => ({ x: 5 + 4 * k + 0.2 * Math.random(), y: (k ? 2 : -1.5) + 0.2 * Math.random(),
                                 ell: [0.3, 0.1, 0.2 * k] }));
  dirty.add(s); dirtyXY = true; perf.lastData = t0; perf.pending += performance.now() - t0;
}
sensors.forEach((s, i) => setTimeout(() => setInterval(() => tick(s), 50), i * 16));
let last = 0;
function frame(now) {
  requestAnimationFrame(frame);
  const flowing = now - perf.lastData < 250;
  if (last && flowing) perf.interval.push(now - last);
  last = now;
  if (!dirty.size && !dirtyXY) return;
  const t0 = performance.now();
  DRAW();
  dirty.clear(); dirtyXY = false;
  if (flowing) perf.frame.push(perf.pending + performance.now() - t0);
  perf.pending = 0;
}
new PerformanceObserver(l => { for (const e of l.getEntries()) if (e.startTime - perf.lastData < 250) perf.long++; })
  .observe({ type: "long-animation-frame" });
const pct = (a, p) => { const s = a.slice().sort((x, y) => x - y); return s.length ? s[Math.min(s.length - 1, Math.floor(p / 100 * s.length))] : null; };
window.bench = {
  reset() { perf.frame = []; perf.interval = []; perf.long = 0; },
  stats() { return { frames: perf.interval.length, frame_p50: pct(perf.frame, 50), frame_p99: pct(perf.frame, 99),
    frame_max: pct(perf.frame, 100), interval_p50: pct(perf.interval, 50), interval_p99: pct(perf.interval, 99),
    over_50ms: perf.long, load_ms: window.loadMs }; },
};
requestAnimationFrame(frame);
"""

UPLOT_PAGE = r"""<!doctype html><html><head><link rel="stylesheet" href="uPlot.min.css"></head>
<body style="margin:0;display:grid;grid-template-columns:55% 45%;height:100vh">
<div id="xy"></div><div id="profiles"></div>
<script>const t0 = performance.now();</script><script src="uPlot.iife.min.js"></script>
<script>window.loadMs = performance.now() - t0;
function ellipses(u) {
  const ctx = u.ctx, X = v => u.valToPos(v, "x", true), Y = v => u.valToPos(v, "y", true), m = Math.abs(X(1) - X(0));
  for (const s of sensors) { ctx.strokeStyle = s.color;
    for (const t of s.targets) { ctx.beginPath(); ctx.ellipse(X(t.x), Y(t.y), t.ell[0] * m, t.ell[1] * m, -t.ell[2], 0, 7); ctx.stroke(); } }
}
</script>
<script>
__COMMON__
const pts = uPlot.paths.points();
const series = [{}];
for (const s of sensors) series.push({ stroke: s.color + "50", fill: s.color + "30", paths: pts, points: { show: false, size: 5, width: 0 } },
                                     { stroke: "#000", fill: s.color, paths: pts, points: { show: false, size: 10, width: 1 } });
const xyEl = document.getElementById("xy");
const xy = new uPlot({ mode: 2, width: xyEl.clientWidth, height: xyEl.clientHeight, legend: { show: false }, cursor: { show: false },
  scales: { x: { time: false, auto: false, min: -2, max: 14 }, y: { auto: false, min: -6, max: 6 } }, series,
  axes: [{ label: "x (m)" }, { label: "y (m)" }], hooks: { draw: [ellipses] } },
  [null, ...series.slice(1).map(() => [[], []])], xyEl);
const plots = sensors.map(s => { const el = document.createElement("div"); document.getElementById("profiles").appendChild(el);
  return new uPlot({ width: 600, height: 280, legend: { show: false }, scales: { x: { time: false }, y: { auto: false, min: -60, max: 0 } },
    axes: [{ label: "range (m)" }, { label: "dB FS" }], series: [{}, { stroke: s.color }, { stroke: "#555", dash: [4, 3] }] },
    [xs, s.rx1, s.rx2], el); });
function DRAW() {  // batch(): uPlot draws now, not in a microtask after the frame's timing
  for (const s of dirty) { const u = plots[sensors.indexOf(s)]; u.batch(() => u.setData([xs, s.rx1, s.rx2], false)); }
  if (dirtyXY) { const data = [null];
    for (const s of sensors) { const p = s.trail.flat(); data.push([p.map(t => t.x), p.map(t => t.y)], [s.targets.map(t => t.x), s.targets.map(t => t.y)]); }
    xy.batch(() => xy.setData(data, false)); }
}
</script></body></html>"""

ECHARTS_PAGE = r"""<!doctype html><html><head></head>
<body style="margin:0;display:grid;grid-template-columns:55% 45%;height:100vh">
<div id="xy"></div><div id="profiles"></div>
<script>const t0 = performance.now();</script><script src="echarts.min.js"></script>
<script>window.loadMs = performance.now() - t0;</script>
<script>
__COMMON__
const opt = { animation: false, silent: true };
const xy = echarts.init(document.getElementById("xy"), null, { renderer: "canvas" });
function ellipseItem(params, api) {  // a custom series: one ellipse per target
  const c = api.coord([api.value(0), api.value(1)]), m = Math.abs(api.coord([1, 0])[0] - api.coord([0, 0])[0]);
  return { type: "ellipse", shape: { cx: 0, cy: 0, rx: api.value(2) * m, ry: api.value(3) * m }, x: c[0], y: c[1],
           rotation: api.value(4), style: { fill: "none", stroke: api.visual("color") } };
}
xy.setOption({ animation: false, xAxis: { min: -2, max: 14, name: "x (m)" }, yAxis: { min: -6, max: 6, name: "y (m)" },
  series: sensors.flatMap(s => [{ type: "scatter", symbolSize: 5, itemStyle: { color: s.color, opacity: 0.3 }, data: [] },
                                { type: "scatter", symbolSize: 10, itemStyle: { color: s.color }, data: [] },
                                { type: "custom", renderItem: ellipseItem, itemStyle: { color: s.color }, data: [] }]) });
const plots = sensors.map(s => { const el = document.createElement("div"); el.style.height = "280px";
  document.getElementById("profiles").appendChild(el); const c = echarts.init(el, null, { renderer: "canvas" });
  c.setOption({ animation: false, xAxis: { type: "value", name: "range (m)" }, yAxis: { type: "value", min: -60, max: 0, name: "dB FS" },
    series: [{ type: "line", showSymbol: false, lineStyle: { width: 1, color: s.color }, data: [] },
             { type: "line", showSymbol: false, lineStyle: { width: 1, type: "dashed", color: "#555" }, data: [] }] });
  return c; });
const pairs = a => Array.from(a, (v, i) => [xs[i], v]);
function DRAW() {  // getZr().flush(): ECharts paints now, not in its own animation frame after the timing
  for (const s of dirty) { const c = plots[sensors.indexOf(s)];
    c.setOption({ series: [{ data: pairs(s.rx1) }, { data: pairs(s.rx2) }] }, opt); c.getZr().flush(); }
  if (dirtyXY) { xy.setOption({ series: sensors.flatMap(s => [{ data: s.trail.flat().map(t => [t.x, t.y]) },
    { data: s.targets.map(t => [t.x, t.y]) }, { data: s.targets.map(t => [t.x, t.y, ...t.ell]) }]) }, opt);
    xy.getZr().flush(); }
}
</script></body></html>"""


def fetch_echarts(version: str, into: Path) -> str:
    """echarts@version's dist/echarts.min.js and LICENSE into ``into`` (npm pack); its integrity."""
    out = subprocess.run(["npm", "pack", "--json", f"echarts@{version}"], cwd=into, check=True, capture_output=True,
                         text=True, timeout=300)
    import json

    info = json.loads(out.stdout)[0]
    with tarfile.open(into / info["filename"]) as tar:
        for name in ("package/dist/echarts.min.js", "package/LICENSE"):
            member = tar.getmember(name)
            (into / Path(name).name).write_bytes(tar.extractfile(member).read())
    return info["integrity"]


def measure(browser, page_path: Path, seconds: float, warmup: float) -> dict:
    page = browser.open(page_path.as_uri())
    page.wait_for("window.bench && window.bench.stats().frames > 10", 20.0, "the page to draw")
    time.sleep(warmup)
    page.evaluate("window.bench.reset()")
    time.sleep(seconds)
    stats = page.evaluate("window.bench.stats()")
    page.navigate("about:blank")
    return {k: (round(v, 2) if isinstance(v, float) else v) for k, v in stats.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--echarts", default="6.1.0", help="the ECharts version to compare with (npm)")
    ap.add_argument("--seconds", type=float, default=10.0, help="measured seconds per library")
    ap.add_argument("--warmup", type=float, default=2.0, help="seconds before measuring")
    args = ap.parse_args()
    chromium = harness.tests_module("chromium")
    with tempfile.TemporaryDirectory(prefix="qradar-plotlib-") as tmp:
        tmp = Path(tmp)
        for name in ("uPlot.iife.min.js", "uPlot.min.css"):
            shutil.copyfile(UPLOT / name, tmp / name)
        integrity = fetch_echarts(args.echarts, tmp)
        (tmp / "uplot.html").write_text(UPLOT_PAGE.replace("__COMMON__", COMMON))
        (tmp / "echarts.html").write_text(ECHARTS_PAGE.replace("__COMMON__", COMMON))
        with chromium.Chromium() as browser:
            results = {"uplot@1.6.32": measure(browser, tmp / "uplot.html", args.seconds, args.warmup),
                       f"echarts@{args.echarts}": measure(browser, tmp / "echarts.html", args.seconds, args.warmup)}
        sizes = {"uplot@1.6.32": (UPLOT / "uPlot.iife.min.js").stat().st_size,
                 f"echarts@{args.echarts}": (tmp / "echarts.min.js").stat().st_size}
    for lib, r in results.items():
        r["script_bytes"] = sizes[lib]
    emit({"machine": machine(), "workload": "3 sensors x 20 Hz: 2 x 256-bin profiles and 2 targets + ellipses each",
          "echarts_integrity": integrity, "results": results})


if __name__ == "__main__":
    main()
