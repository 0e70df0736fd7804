// Live plots (uPlot, vendored): points are appended as they come (telemetry at 50 Hz, status at 10 Hz) and the
// charts are redrawn at most REDRAW_HZ times a second, in an animation frame, so that the page keeps its frame rate.

const REDRAW_HZ = 8;
const COLOURS = ["#1d5fa8", "#d2691e", "#2e8b57"];

class Strip {
  // One chart of a sliding time window: x in seconds, one array per series.
  constructor(element, title, series, windowS, yRange) {
    this.windowS = windowS;
    this.data = [[], ...series.map(() => [])];
    this.dirty = false;
    const width = Math.max(300, element.clientWidth || 600);
    this.plot = new uPlot({
      title, width, height: 170, legend: { show: true, live: false },
      cursor: { show: false }, // no hover work while telemetry streams
      scales: { x: { time: false }, y: yRange ? { range: yRange } : {} },
      axes: [{ label: "s", size: 36 }, { size: 56 }],
      series: [{}, ...series],
    }, this.data, element);
    new ResizeObserver(() => {
      const w = Math.max(300, element.clientWidth);
      if (Math.abs(w - this.plot.width) > 4) this.plot.setSize({ width: w, height: 170 });
    }).observe(element);
  }

  push(time, values) {
    const data = this.data;
    if (data[0].length && time < data[0][data[0].length - 1]) this.clear(); // a restarted daemon counts from 0
    data[0].push(time);
    values.forEach((value, i) => data[i + 1].push(value ?? null));
    // drop what left the window, in blocks (shifting one by one would be quadratic)
    const since = time - this.windowS;
    if (data[0][0] < since - this.windowS * 0.25) {
      let cut = 0;
      while (cut < data[0].length && data[0][cut] < since) cut++;
      for (const column of data) column.splice(0, cut);
    }
    this.dirty = true;
  }

  clear() {
    for (const column of this.data) column.length = 0;
  }

  draw() {
    if (!this.dirty) return;
    this.dirty = false;
    this.plot.setData(this.data);
  }
}

export class Plots {
  constructor(labels, simulated) {
    const line = (label, colour, dash) => ({ label, stroke: colour, width: 2, dash, points: { show: false } });
    const volumeSeries = [line("target", "#111", [8, 6]), line("estimate", COLOURS[0])];
    if (simulated) volumeSeries.push(line("true (simulated)", "#b3141b"));
    this.volume = new Strip(document.getElementById("plot-volume"), "Gland volume (ml)", volumeSeries, 120);
    this.pressure = new Strip(document.getElementById("plot-pressure"), "Chamber pressure and setpoint (kPa)", [
      ...labels.map((label, i) => line(label, COLOURS[i % 3])),
      ...labels.map((label, i) => line(`${label} setpoint`, COLOURS[i % 3], [6, 5])),
    ], 30);
    this.drive = new Strip(document.getElementById("plot-drive"), "Blower drive (0-1)",
      labels.map((label, i) => line(label, COLOURS[i % 3])), 30, [0, 1]);
    this.simulated = simulated;
    this.scheduled = false;
    this.lastDrawMs = 0;
  }

  telemetry(frame) {
    this.pressure.push(frame.time_s, [...frame.pressures_kpa, ...frame.setpoints_kpa]);
    this.drive.push(frame.time_s, frame.drive_levels);
    this.schedule();
  }

  status(status) {
    const values = [status.target_volume_ml, status.estimated_volume_ml];
    if (this.simulated) values.push(status.plant_volume_ml);
    this.volume.push(status.uptime_s, values);
    this.schedule();
  }

  schedule() {
    if (this.scheduled) return;
    this.scheduled = true;
    const wait = Math.max(0, 1000 / REDRAW_HZ - (performance.now() - this.lastDrawMs));
    setTimeout(() => this.drawInTurn([this.volume, this.pressure, this.drive]), wait);
  }

  drawInTurn(strips) {
    // one chart per animation frame: three redraws in one task made it long enough to drop frames
    requestAnimationFrame(() => {
      strips[0].draw();
      if (strips.length > 1) {
        this.drawInTurn(strips.slice(1));
      } else {
        this.scheduled = false;
        this.lastDrawMs = performance.now();
      }
    });
  }
}
