// The live page of jobs: the caller's jobs (GET /jobs, polled), the selected job's event
// stream (GET /jobs/{id}/events, read with fetch so that it carries the Authorization
// header), its convergence plot, result plots and files, cancel and resume.
"use strict";

const TOKEN_KEY = "ocpar.token";
const POLL_MS = 1000;
const FINAL = new Set(["succeeded", "failed", "cancelled"]);
const LOG_LINES = 400;
// the figure plotted for each scheme's progress lines, when the line carries it
const MAIN_FIGURE = { formation: ["cost"], macs: ["hypervolume", "archive"] };
// figures that count or time things: never the main figure of a line
const COUNTERS = new Set(["superstep", "wall", "overhead", "iteration", "evaluations",
  "archive", "finished", "flight", "agents", "equidistance", "coupling", "spread", "rounds"]);

const $ = (id) => document.getElementById(id);
const state = {
  token: localStorage.getItem(TOKEN_KEY) || "",
  jobs: new Map(), // id -> record
  selected: null, // id of the job in the detail panel
  stream: null, // AbortController of the selected job's event stream
  resultsShown: null, // "id state" whose plots and files are shown
  objectUrls: [],
  pollTimer: null,
  pollFailed: false, // the message shows the last GET /jobs error
  streamed: null, // {job, at}: the last record of the selected job's stream, and when
};
let plot = null;

function say(text, isError) {
  const message = $("message");
  message.textContent = text;
  message.classList.toggle("error", Boolean(isError));
}

// fetch with the token; a non-2xx answer throws an Error with the server's detail
async function api(path, options = {}) {
  const headers = new Headers(options.headers || {});
  headers.set("Authorization", `Bearer ${state.token}`);
  const response = await fetch(path, { ...options, headers });
  if (!response.ok) {
    let detail = response.statusText;
    try {
      const body = await response.json();
      if (body && body.detail !== undefined) {
        detail = typeof body.detail === "string" ? body.detail : JSON.stringify(body.detail);
      }
    } catch (_) { /* not JSON */ }
    const error = new Error(`${options.method || "GET"} ${path}: ${response.status} ${detail}`);
    error.status = response.status;
    throw error;
  }
  return response;
}

// an ISO 8601 time as local "YYYY-MM-DD HH:MM:SS"
function formatTime(iso) {
  if (!iso) return "";
  const date = new Date(iso);
  if (Number.isNaN(date.getTime())) return iso;
  const two = (n) => String(n).padStart(2, "0");
  return `${date.getFullYear()}-${two(date.getMonth() + 1)}-${two(date.getDate())} ` +
    `${two(date.getHours())}:${two(date.getMinutes())}:${two(date.getSeconds())}`;
}

// ---- the jobs table --------------------------------------------------------------------

function button(label, action, id) {
  const element = document.createElement("button");
  element.type = "button";
  element.textContent = label;
  element.dataset.action = action;
  element.setAttribute("aria-label", `${label} job ${id}`);
  return element;
}

function createRow(id) {
  const row = document.createElement("tr");
  row.dataset.jobId = id;
  for (const name of ["job-id", "scheme", "problem", "state", "progress", "submitted",
    "finished", "headline", "actions"]) {
    const cell = document.createElement(name === "job-id" ? "th" : "td");
    if (name === "job-id") cell.scope = "row";
    cell.className = name;
    row.appendChild(cell);
  }
  row.querySelector(".job-id").textContent = id;
  const bar = document.createElement("progress");
  bar.setAttribute("aria-label", `progress of job ${id}`);
  const count = document.createElement("span");
  count.className = "supersteps";
  row.querySelector(".progress").append(bar, count);
  row.querySelector(".actions").append(button("Show", "show", id),
    button("Cancel", "cancel", id), button("Resume", "resume", id));
  return row;
}

// progress: supersteps done; indeterminate while running (the number of outer iterations
// is not known ahead), empty while queued, full once final
function updateRow(row, job) {
  row.dataset.state = job.state;
  row.querySelector(".scheme").textContent = job.scheme || "";
  row.querySelector(".problem").textContent = job.problem || "";
  const stateCell = row.querySelector(".state");
  stateCell.textContent = job.state;
  stateCell.title = job.reason || "";
  const bar = row.querySelector("progress");
  bar.max = 1;
  if (job.state === "running") bar.removeAttribute("value");
  else bar.value = FINAL.has(job.state) ? 1 : 0;
  const supersteps = job.supersteps || 0;
  row.querySelector(".supersteps").textContent =
    ` ${supersteps} superstep${supersteps === 1 ? "" : "s"}`;
  row.dataset.supersteps = supersteps;
  const submitted = row.querySelector(".submitted");
  submitted.textContent = formatTime(job.submitted);
  submitted.title = job.submitted || "";
  const finished = row.querySelector(".finished");
  finished.textContent = formatTime(job.finished);
  finished.title = job.finished || "";
  // the result's title, else why the job ended so (failed, cancelled), else its status
  row.querySelector(".headline").textContent =
    job.headline || job.reason || job.result_status || "";
  row.querySelector('[data-action="cancel"]').disabled = FINAL.has(job.state);
  row.querySelector('[data-action="resume"]').disabled =
    !(job.state === "cancelled" || job.state === "failed");
  row.classList.toggle("selected", job.id === state.selected);
}

function renderJobs(jobs) {
  const body = $("job-rows");
  const rows = new Map([...body.querySelectorAll("tr")].map((r) => [r.dataset.jobId, r]));
  state.jobs = new Map(jobs.map((job) => [job.id, job]));
  jobs.forEach((job, index) => {
    let row = rows.get(job.id);
    if (!row) row = createRow(job.id);
    rows.delete(job.id);
    updateRow(row, job);
    if (body.children[index] !== row) body.insertBefore(row, body.children[index] || null);
  });
  for (const row of rows.values()) row.remove();
  $("no-jobs").hidden = jobs.length > 0;
}

async function refreshJobs() {
  if (!state.token) return;
  try {
    const asked = performance.now();
    const response = await api("/jobs");
    let { jobs } = await response.json();
    // a record the event stream brought after this request left is newer than the list's
    const streamed = state.streamed;
    if (streamed !== null && streamed.at > asked) {
      jobs = jobs.map((job) => (job.id === streamed.job.id ? streamed.job : job));
    }
    renderJobs(jobs);
    if (state.selected === null && jobs.length > 0) {
      // the newest running job, else the newest
      selectJob((jobs.find((job) => job.state === "running") || jobs[0]).id);
    }
    else if (state.selected !== null && state.jobs.has(state.selected)) {
      showRecord(state.jobs.get(state.selected));
    }
    if (state.pollFailed) say(""); // the list's own error is over
    state.pollFailed = false;
  } catch (error) {
    state.pollFailed = true;
    say(error.message, true);
  }
}

function poll() {
  clearTimeout(state.pollTimer);
  refreshJobs().finally(() => {
    state.pollTimer = setTimeout(poll, POLL_MS);
  });
}

// ---- the selected job ------------------------------------------------------------------

function showRecord(job) {
  if (job.id !== state.selected) return;
  state.jobs.set(job.id, job);
  const row = document.querySelector(`#job-rows tr[data-job-id="${CSS.escape(job.id)}"]`);
  if (row) updateRow(row, job);
  const detail = $("detail");
  detail.dataset.state = job.state;
  $("detail-state").textContent = job.state;
  $("detail-reason").textContent = job.reason ? `(${job.reason})` : "";
  $("detail-headline").textContent = job.headline || "";
  if (FINAL.has(job.state)) {
    if (state.resultsShown !== `${job.id} ${job.state}`) {
      state.resultsShown = `${job.id} ${job.state}`;
      loadResults(job.id);
    }
  } else if (state.resultsShown !== null) {
    // resumed: its results are gone until it ends again, and its stream starts over
    state.resultsShown = null;
    clearResults();
    openStream(job.id);
  }
}

function selectJob(id) {
  state.selected = id;
  state.resultsShown = null;
  for (const row of document.querySelectorAll("#job-rows tr")) {
    row.classList.toggle("selected", row.dataset.jobId === id);
  }
  $("detail").hidden = false;
  $("detail").dataset.jobId = id;
  $("detail-id").textContent = id;
  clearResults();
  openStream(id);
  const job = state.jobs.get(id);
  if (job) showRecord(job);
}

function clearResults() {
  for (const url of state.objectUrls) URL.revokeObjectURL(url);
  state.objectUrls = [];
  $("plots").replaceChildren(noneYet("p"));
  $("files").replaceChildren(noneYet("li"));
}

function noneYet(tag) {
  const element = document.createElement(tag);
  element.className = "none";
  element.textContent = "None yet.";
  return element;
}

// the figure plotted from a progress event: the scheme's own, else (a scheme without one:
// pursuit, whose lines carry "last <headline>") the first that is not a counter or a time;
// once chosen, a job's plot keeps that figure
function mainFigure(scheme, figures, chosen) {
  const usable = (name) => Number.isFinite(figures[name]);
  if (chosen) return usable(chosen) ? chosen : undefined;
  const own = MAIN_FIGURE[scheme];
  if (own && own.length > 0) return own.find(usable);
  const names = Object.keys(figures).filter(usable);
  const last = names.find((name) => /^last\b/.test(name));
  if (last !== undefined) return last;
  return names.find((name) => !name.split(/[\s_]+/).some((word) => COUNTERS.has(word)));
}

// the job's progress lines, the last LOG_LINES of them shown (written every 150 ms at most)
const log = { lines: [], pending: false };

function appendLog(line) {
  log.lines.push(line);
  if (log.lines.length > 2 * LOG_LINES) log.lines = log.lines.slice(-LOG_LINES);
  if (log.pending) return;
  log.pending = true;
  setTimeout(() => {
    log.pending = false;
    const element = $("log");
    element.textContent = log.lines.slice(-LOG_LINES).join("\n");
    element.scrollTop = element.scrollHeight;
  }, 150);
}

function clearLog() {
  log.lines = [];
  $("log").textContent = "";
}

function onEvent(id, name, data) {
  if (id !== state.selected) return;
  if (name === "progress") {
    appendLog(data.line);
    const job = state.jobs.get(id);
    const figures = data.figures || {};
    const figure = mainFigure(job ? job.scheme : "", figures, plot.figure);
    if (figure === undefined) return;
    const iteration = Number.isFinite(figures.iteration) ? figures.iteration : null;
    const x = Number.isInteger(data.superstep) ? data.superstep
      : iteration !== null ? iteration : plot.points.length;
    const xLabel = Number.isInteger(data.superstep) ? "superstep"
      : iteration !== null ? "iteration" : "line";
    plot.add(x, figures[figure], figure, xLabel);
  } else if (name === "state" || name === "end") {
    state.streamed = { job: data, at: performance.now() };
    showRecord(data);
  }
}

// Server-sent events over fetch: blocks separated by a blank line, "event:" and "data:"
// fields (lines may end in \r\n); the stream replays the job's log from its start.
async function readStream(id, signal) {
  const response = await api(`/jobs/${encodeURIComponent(id)}/events`, {
    signal, headers: { Accept: "text/event-stream" },
  });
  const reader = response.body.pipeThrough(new TextDecoderStream()).getReader();
  let buffer = "";
  let ended = false;
  for (;;) {
    const { value, done } = await reader.read();
    if (done) break;
    buffer += value;
    // keep a trailing \r: it may be the first half of a \r\n
    const cut = buffer.endsWith("\r") ? buffer.length - 1 : buffer.length;
    const text = buffer.slice(0, cut).replace(/\r\n?/g, "\n");
    const rest = buffer.slice(cut);
    const blocks = text.split("\n\n");
    buffer = blocks.pop() + rest;
    for (const block of blocks) {
      let name = "message";
      const data = [];
      for (const line of block.split("\n")) {
        if (line === "" || line.startsWith(":")) continue;
        const colon = line.indexOf(":");
        const field = colon < 0 ? line : line.slice(0, colon);
        const content = colon < 0 ? "" : line.slice(colon + 1).replace(/^ /, "");
        if (field === "event") name = content;
        else if (field === "data") data.push(content);
      }
      if (data.length === 0) continue;
      onEvent(id, name, JSON.parse(data.join("\n")));
      if (name === "end") ended = true;
    }
  }
  return ended;
}

function openStream(id) {
  if (state.stream) state.stream.abort();
  const controller = new AbortController();
  state.stream = controller;
  plot.reset("");
  clearLog();
  readStream(id, controller.signal).then((ended) => {
    // the connection dropped before the job ended: read it again from the start
    if (!ended && !controller.signal.aborted) setTimeout(() => reopen(id, controller), 2000);
  }, (error) => {
    if (controller.signal.aborted) return;
    say(error.message, true);
    if (error.status === undefined || error.status >= 500) {
      setTimeout(() => reopen(id, controller), 2000);
    }
  });
}

function reopen(id, controller) {
  if (state.stream === controller && state.selected === id) openStream(id);
}

// ---- results: plots and files, fetched with the token ------------------------------------

async function blobUrl(id, name) {
  const response = await api(`/jobs/${encodeURIComponent(id)}/files/${encodeURIComponent(name)}`);
  const url = URL.createObjectURL(await response.blob());
  state.objectUrls.push(url);
  return url;
}

async function download(id, name) {
  try {
    const url = await blobUrl(id, name);
    const save = document.createElement("a");
    save.href = url;
    save.download = name;
    document.body.appendChild(save);
    save.click();
    save.remove();
  } catch (error) {
    say(error.message, true);
  }
}

async function loadResults(id) {
  let files;
  try {
    files = (await (await api(`/jobs/${encodeURIComponent(id)}/files`)).json()).files;
  } catch (error) {
    if (error.status !== 404) say(error.message, true);
    return;
  }
  if (id !== state.selected) return;
  const list = $("files");
  list.replaceChildren();
  for (const file of files) {
    const item = document.createElement("li");
    const link = document.createElement("a");
    link.href = "#";
    link.className = "file-link";
    link.dataset.file = file.name;
    link.textContent = file.name;
    link.setAttribute("aria-label", `download ${file.name}`);
    link.addEventListener("click", (event) => {
      event.preventDefault();
      download(id, file.name);
    });
    item.append(link, file.size === null ? " (drawn when opened)" : ` (${file.size} bytes)`);
    list.appendChild(item);
  }
  if (files.length === 0) list.appendChild(noneYet("li"));
  const plots = $("plots");
  plots.replaceChildren();
  const images = files.filter((file) => /\.png$/i.test(file.name));
  for (const file of images) {
    const figure = document.createElement("figure");
    const image = document.createElement("img");
    image.className = "result-plot";
    image.dataset.file = file.name;
    image.alt = `plot ${file.name} of job ${id}`;
    const caption = document.createElement("figcaption");
    caption.textContent = file.name;
    figure.append(image, caption);
    plots.appendChild(figure);
    blobUrl(id, file.name).then((url) => { image.src = url; },
      (error) => say(error.message, true));
  }
  if (images.length === 0) plots.appendChild(noneYet("p"));
}

// ---- actions ---------------------------------------------------------------------------

async function act(action, id) {
  const path = `/jobs/${encodeURIComponent(id)}`;
  try {
    if (action === "show") {
      selectJob(id);
      return;
    }
    if (action === "cancel") {
      await api(path, { method: "DELETE" });
      say(`Cancel of ${id} requested: it stops at its next superstep boundary.`);
    } else if (action === "resume") {
      await api(`${path}/resume`, { method: "POST" });
      say(`${id} resumed from its checkpoint.`);
    }
    await refreshJobs();
  } catch (error) {
    say(error.message, true);
  }
}

// "agents=12 outer=\"sqp\" quiet=true" -> {agents: 12, outer: "sqp", quiet: true}
function parseOverrides(text) {
  const overrides = {};
  const pattern = /([A-Za-z_][\w.-]*)\s*=\s*("(?:[^"\\]|\\.)*"|[^\s,]+)/g;
  let rest = text;
  for (const match of text.matchAll(pattern)) {
    const [, key, raw] = match;
    let value;
    try { value = JSON.parse(raw); } catch (_) { value = raw; }
    overrides[key] = value;
    rest = rest.replace(match[0], "");
  }
  if (rest.replace(/[\s,]/g, "") !== "") {
    throw new Error(`overrides: cannot read "${rest.trim()}" (expected KEY=VALUE pairs)`);
  }
  return overrides;
}

async function submitJob(event) {
  event.preventDefault();
  try {
    const body = { config: $("config").value.trim() };
    const overrides = parseOverrides($("overrides").value);
    if (Object.keys(overrides).length > 0) body.set = overrides;
    const response = await api("/jobs", {
      method: "POST", body: JSON.stringify(body),
      headers: { "Content-Type": "application/json" },
    });
    const job = await response.json();
    say(`Submitted ${job.id}.`);
    await refreshJobs();
    selectJob(job.id);
  } catch (error) {
    say(error.message, true);
  }
}

function useToken(token) {
  state.token = token;
  if (token) localStorage.setItem(TOKEN_KEY, token);
  else localStorage.removeItem(TOKEN_KEY);
  state.selected = null;
  if (state.stream) state.stream.abort();
  $("detail").hidden = true;
  renderJobs([]);
  say(token ? "" : "Enter a token to see your jobs.");
  if (token) poll();
  else clearTimeout(state.pollTimer);
}

document.addEventListener("DOMContentLoaded", () => {
  plot = new window.ConvergencePlot($("convergence"), $("convergence-caption"));
  $("token").value = state.token;
  $("token-form").addEventListener("submit", (event) => {
    event.preventDefault();
    useToken($("token").value.trim());
  });
  $("forget-token").addEventListener("click", () => {
    $("token").value = "";
    useToken("");
  });
  $("submit-form").addEventListener("submit", submitJob);
  $("job-rows").addEventListener("click", (event) => {
    const target = event.target.closest("button[data-action]");
    if (target) act(target.dataset.action, target.closest("tr").dataset.jobId);
  });
  useToken(state.token);
});
