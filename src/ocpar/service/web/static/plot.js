// The live convergence plot: one figure against the superstep, drawn as inline SVG.
// The y axis is logarithmic when every value is positive and they span two decades or more.
"use strict";

const SVG_NS = "http://www.w3.org/2000/svg";
const RENDER_MS = 150;
// points drawn as markers (each with its value) up to this many; beyond, the line only
const MAX_MARKERS = 600;

function svgElement(name, attributes, text) {
  const element = document.createElementNS(SVG_NS, name);
  for (const [key, value] of Object.entries(attributes || {})) {
    element.setAttribute(key, String(value));
  }
  if (text !== undefined) element.textContent = text;
  return element;
}

// Ticks at 1, 2 or 5 times a power of ten covering [low, high], about `count` of them,
// spaced at least minStep apart.
function linearTicks(low, high, count, minStep = 0) {
  const raw = Math.max((high - low) / Math.max(count, 1), minStep);
  const power = Math.pow(10, Math.floor(Math.log10(raw)));
  const step = [1, 2, 5, 10].map((m) => m * power).find((s) => s >= raw) || 10 * power;
  const ticks = [];
  for (let t = Math.ceil(low / step) * step; t <= high + step * 1e-9; t += step) {
    ticks.push(Math.abs(t) < step * 1e-9 ? 0 : t);
  }
  return { ticks, step };
}

// A tick label with as many digits as the tick step resolves.
function tickLabel(value, step) {
  if (value === 0) return "0";
  const magnitude = Math.floor(Math.log10(Math.abs(value)));
  const resolution = Math.floor(Math.log10(step));
  if (magnitude >= 5 || magnitude <= -4) {
    return value.toExponential(Math.min(Math.max(magnitude - resolution, 0), 12));
  }
  return value.toFixed(Math.min(Math.max(-resolution, 0), 12));
}

class ConvergencePlot {
  // container: the element the SVG goes into; caption: the element describing it in words
  constructor(container, caption) {
    this.container = container;
    this.caption = caption;
    this.width = 640;
    this.height = 260;
    this.margin = { left: 78, right: 16, top: 12, bottom: 38 };
    this.reset("");
  }

  // Start over for another job; `figure` names the plotted value (e.g. "cost").
  reset(figure) {
    this.points = [];
    this.figure = figure;
    this.xLabel = "superstep";
    this.pending = false;
    this.render();
  }

  // Add one point (x: superstep or iteration, named xLabel; y: the figure); drawn at most
  // every RENDER_MS (a replayed stream brings thousands of points at once).
  add(x, y, figure, xLabel) {
    if (!Number.isFinite(x) || !Number.isFinite(y)) return;
    if (figure) this.figure = figure;
    if (xLabel) this.xLabel = xLabel;
    this.points.push([x, y]);
    if (!this.pending) {
      this.pending = true;
      setTimeout(() => {
        this.pending = false;
        this.render();
      }, RENDER_MS);
    }
  }

  render() {
    const { width, height, margin, points } = this;
    const svg = svgElement("svg", {
      id: "convergence-plot", viewBox: `0 0 ${width} ${height}`, role: "img",
      "aria-labelledby": "convergence-caption", "data-points": points.length,
      "data-figure": this.figure || "",
    });
    const plotWidth = width - margin.left - margin.right;
    const plotHeight = height - margin.top - margin.bottom;
    svg.appendChild(svgElement("rect", {
      class: "frame", x: margin.left, y: margin.top, width: plotWidth, height: plotHeight,
    }));
    if (points.length === 0) {
      svg.setAttribute("data-scale", "none");
      this.container.replaceChildren(svg);
      this.caption.textContent = this.figure
        ? `No ${this.figure} values yet.` : "Waiting for progress lines.";
      return;
    }
    let xLow = Infinity, xHigh = -Infinity, yLow = Infinity, yHigh = -Infinity;
    let integerX = true;
    for (const [x, y] of points) {
      xLow = Math.min(xLow, x); xHigh = Math.max(xHigh, x);
      yLow = Math.min(yLow, y); yHigh = Math.max(yHigh, y);
      integerX = integerX && Number.isInteger(x);
    }
    if (xHigh === xLow) { xLow -= 1; xHigh += 1; }
    const log = yLow > 0 && yHigh / yLow >= 100;
    svg.setAttribute("data-scale", log ? "log" : "linear");
    const f = log ? Math.log10 : (v) => v;
    let fLow = f(yLow), fHigh = f(yHigh);
    if (fHigh === fLow) {
      const pad = Math.abs(fLow) * 1e-3 || 1;
      fLow -= pad; fHigh += pad;
    }
    const pad = (fHigh - fLow) * 0.05;
    fLow -= pad; fHigh += pad;
    const px = (x) => margin.left + ((x - xLow) / (xHigh - xLow)) * plotWidth;
    const py = (y) => margin.top + (1 - (f(y) - fLow) / (fHigh - fLow)) * plotHeight;

    const axes = svgElement("g", { class: "axes" });
    // y ticks: decades on a log axis, 1-2-5 steps on a linear one
    let yTicks;
    if (log) {
      yTicks = [];
      for (let e = Math.ceil(fLow); e <= Math.floor(fHigh); e++) {
        yTicks.push([Math.pow(10, e), `1e${e}`]);
      }
    } else {
      const { ticks, step } = linearTicks(fLow, fHigh, 5);
      yTicks = ticks.map((t) => [t, tickLabel(t, step)]);
    }
    for (const [value, label] of yTicks) {
      const y = py(value);
      axes.appendChild(svgElement("line", {
        class: "grid", x1: margin.left, x2: margin.left + plotWidth, y1: y, y2: y,
      }));
      axes.appendChild(svgElement("text", {
        class: "tick", x: margin.left - 6, y: y + 4, "text-anchor": "end",
      }, label));
    }
    const xStep = linearTicks(xLow, xHigh, 8, integerX ? 1 : 0);
    for (const value of xStep.ticks) {
      const x = px(value);
      axes.appendChild(svgElement("line", {
        class: "grid", x1: x, x2: x, y1: margin.top, y2: margin.top + plotHeight,
      }));
      axes.appendChild(svgElement("text", {
        class: "tick", x, y: margin.top + plotHeight + 16, "text-anchor": "middle",
      }, tickLabel(value, xStep.step)));
    }
    axes.appendChild(svgElement("text", {
      class: "label", x: margin.left + plotWidth / 2, y: height - 4, "text-anchor": "middle",
    }, this.xLabel));
    axes.appendChild(svgElement("text", {
      class: "label", x: 12, y: margin.top + plotHeight / 2, "text-anchor": "middle",
      transform: `rotate(-90 12 ${margin.top + plotHeight / 2})`,
    }, this.figure + (log ? " (log)" : "")));
    svg.appendChild(axes);

    svg.appendChild(svgElement("polyline", {
      class: "line",
      points: points.map(([x, y]) => `${px(x).toFixed(1)},${py(y).toFixed(1)}`).join(" "),
    }));
    const dots = svgElement("g", { class: "points" });
    for (const [x, y] of points.length <= MAX_MARKERS ? points : []) {
      const dot = svgElement("circle", {
        class: "pt", cx: px(x), cy: py(y), r: 3, "data-x": x, "data-y": y,
      });
      dot.appendChild(svgElement("title", {}, `${x}: ${this.figure} ${y}`));
      dots.appendChild(dot);
    }
    svg.appendChild(dots);
    this.container.replaceChildren(svg);
    const [lastX, lastY] = points[points.length - 1];
    this.caption.textContent = `${this.figure}: ${points.length} points` +
      `${log ? " (log scale)" : ""}; latest (${this.xLabel} ${lastX}): ${lastY}`;
  }
}

window.ConvergencePlot = ConvergencePlot;
