// The operator console: the daemon's status and event stream; START / ABORT / RESET go to the
// same control handler as the panel's buttons and `tbp scan` / `tbp abort` / `tbp reset`.
import { getJSON, send, el, fmt, personName } from "/static/common.js";

const $ = (id) => document.getElementById(id);
const hooks = { events: [], status: null };
window.tbpConsole = hooks;
let state = null;
// The daemon's state lists (daemon/rig/states.py, in every status): "job" (a scan or calibration
// rotation runs) and "active" (the beam may move under it: ABORT is taken).
let states = { active: [], job: [] };
let counts = { captured: 0, verified: 0 };
let poses = 336;

function pill(text, kind) { return el("span", { class: `pill ${kind}` }, text); }

// A status box is drawn again only when what it shows changes (``data``, compared as JSON):
// redrawn at every status, a link replaced under the pointer between press and release is
// never clicked, and a fault's text cannot be selected and copied. ``build`` returns the box's
// children; null ones are left out.
const drawn = new Map();
function redraw(id, data, build) {
  const key = JSON.stringify(data ?? null);
  if (drawn.get(id) === key) return;
  drawn.set(id, key);
  $(id).replaceChildren(...build().filter((child) => child !== null && child !== undefined));
}

function showState(name, cause) {
  state = name;
  $("state").replaceChildren(pill(name, states.job.includes(name) ? "busy" : name));
  if (cause !== undefined) $("cause").textContent = cause;
  $("start").disabled = name !== "IDLE";
  $("abort").disabled = !states.active.includes(name);
  $("reset").disabled = name !== "FAULT";
}

function showStatus(s) {
  hooks.status = s;
  if (s.states && JSON.stringify(s.states) !== JSON.stringify(states)) {
    states = s.states;
    showState(s.state);
  } else if (s.state !== state) showState(s.state);
  $("angle").textContent = s.beam_angle_deg === null ? "–" : `${fmt(s.beam_angle_deg, 1)}°`;
  $("speed").textContent = s.beam_speed_deg_s === null ? "–" : `${fmt(s.beam_speed_deg_s, 1)}°/s`;
  $("scan-id").textContent = s.scan_id || "";
  showJobTime(s.job_time);
  const present = s.beam_angle_deg !== null;
  redraw("devices", [s.healthy, s.ready, present, s.devices], () => [
    el("div", {}, "Daemon ", pill(s.healthy ? "healthy" : "unhealthy", s.healthy ? "ok" : "bad")),
    el("div", {}, "Rig ", pill(s.ready ? "ready" : "NOT READY", s.ready ? "ok" : "bad")),
    el("div", {}, "Beam drive ", pill(present ? "encoder live" : "no encoder", present ? "ok" : "bad")),
    ...(s.devices || []).map((d) => el("div", { class: "device", title: d.address },
      `${d.device} `, pill(d.ok ? "answers" : "missing", d.ok ? "ok" : "bad")))]);
  const missing = (s.devices || []).filter((d) => !d.ok);
  redraw("faults", [s.fault_causes, missing, s.recovered_scans], () => [
    ...s.fault_causes.map((c) => el("div", {}, `Fault: ${c.text || c.detail || c}`)),
    ...missing.map((d) => el("div", {}, `${d.device} (${d.address}): ${d.error || "not answering"}; ${d.check}`)),
    ...(s.recovered_scans || []).map((r) => el("div", { class: "muted" }, `Recovered interrupted scan ${r.scan_id}: ${r.reason}`))]);
  showLast(s.last_scan);
  showArchive(s.archive);
}

// The export queue (when the site file names an archive): waiting, sending, sent, failed.
function showArchive(a) {
  redraw("archive", a, () => {
    if (!a) return [];
    const c = a.counts;
    const sending = a.sending ? `, sending ${a.sending.folder} (${a.sending.sent} / ${a.sending.total ?? "?"})` : "";
    const retry = a.retry_in_s !== null ? `, next try in ${fmt(a.retry_in_s, 0)} s` : "";
    return [el("div", {}, "Archive ", pill(c.failed ? "failed" : c.pending || c.sending ? "waiting" : "up to date",
      c.failed ? "bad" : "ok"), ` ${a.destination}: ${c.sent} sent, ${c.pending} waiting${sending}${retry}`),
    ...a.problems.map((p) => el("div", { class: p.state === "failed" ? "error" : "muted" }, `${p.folder}: ${p.error}`))];
  });
}

// The last scan's outcome in colour (COMPLETED green, PARTIAL yellow, ABORTED orange, FAULTED
// red), its images, and for each phone the images missing and why; phones dropped are named.
function showLast(last) {
  redraw("last", last, () => {
    if (!last) return [];
    const name = last.folder.split("/").pop();
    const phones = Object.entries(last.missing_by_phone || {}).map(([camera, reasons]) => el("li", {},
      `${camera}: ${Object.values(reasons).reduce((a, b) => a + b, 0)} missing (`,
      Object.entries(reasons).map(([why, n]) => `${n} ${why.replace("_", " ")}`).join(", "), ")"));
    const dropped = (last.dropped_phones || []).filter((d) => !d.rejoined)
      .map((d) => el("li", {}, `${d.camera} dropped after ${d.failures} failed captures in a row (${d.pass_name} pass): ${d.first_error}`));
    return [el("b", {}, "Last scan "), `${last.scan_id} `,
      el("span", { class: `pill ${last.outcome}`, id: "last-outcome" }, last.outcome),
      ` ${last.verified} of ${last.verified + last.missing} images in the folder, ${last.missing} missing `,
      el("a", { id: "report-link", href: `/scans/${encodeURIComponent(name)}/report/` }, "QA report"), " · ",
      el("a", { href: `/scans/${encodeURIComponent(name)}` }, "open in the viewer"),
      last.reason ? el("div", { class: "why" }, last.reason) : null,
      phones.length || dropped.length ? el("ul", { id: "last-missing", class: "why" }, ...phones, ...dropped) : null];
  });
}

// An event's clock time: local wall time from its UTC stamp (not the daemon's loop seconds).
const clock = (utc) => (utc ? new Date(utc).toLocaleTimeString([], { hour: "2-digit", minute: "2-digit", second: "2-digit" }) : "--:--:--");

// A duration as a person reads it: "45 s", "3 min 05 s".
function span(s) {
  if (s === null || s === undefined) return "–";
  const whole = Math.max(0, Math.round(s));
  return whole < 60 ? `${whole} s` : `${Math.floor(whole / 60)} min ${String(whole % 60).padStart(2, "0")} s`;
}

// The log's lines, newest first; the job's end in its outcome's colour.
function logLine(e) {
  const about = e.data && e.data.camera ? ` ${e.data.camera}${e.data.error ? `: ${e.data.error}` : ""}` : "";
  const what = `${e.kind === "transition" ? `${e.previous} → ${e.state}` : e.state}  ${e.cause}${about}`;
  const outcome = e.data && e.data.outcome;
  const log = $("log");
  log.prepend(el("div", { class: "event" }, el("span", { class: "clock" }, clock(e.utc)), "  ",
    outcome ? el("span", { class: `pill ${outcome}` }, what) : what));
  while (log.childElementCount > 200) log.lastChild.remove();
}

// The history the daemon kept (sent first on every connection): the log starts from it, and live
// events it already held (by their running number) are not shown twice.
let lastSeq = 0;
function showHistory(events) {
  hooks.history = events;
  $("log").replaceChildren();
  events.forEach(logLine);
  lastSeq = events.length ? events[events.length - 1].seq : 0;
}

// The running job's elapsed time and the beam's schedule left (daemon/jobs/scan_time.py).
function showJobTime(t) {
  $("job-time").textContent = !t ? ""
    : `Elapsed ${span(t.elapsed_s)}, ${t.remaining_s === null ? "time left not known in this state"
      : `about ${span(t.remaining_s)} of the beam's schedule left`}`;
}

function onEvent(e) {
  if (e.seq <= lastSeq) return;
  lastSeq = e.seq;
  hooks.events.push({ ...e, received_ms: performance.timeOrigin + performance.now() });
  if (e.kind === "transition") {
    showState(e.state, e.cause);
    if (e.state === "PREPARING") counts = { captured: 0, verified: 0 };
    logLine(e);
  } else if (e.cause === "captured") {
    counts.captured = e.data.captured;
    if (e.data.angle_deg !== undefined) $("angle").textContent = `${fmt(e.data.angle_deg, 1)}°`;
  } else if (e.cause === "verified") {
    counts.verified = e.data.verified;
  } else logLine(e);
  $("captured").textContent = counts.captured;
  $("verified").textContent = counts.verified;
  $("bar-captured").style.width = `${Math.min(100, (100 * counts.captured) / poses)}%`;
  $("bar-verified").style.width = `${Math.min(100, (100 * counts.verified) / poses)}%`;
}

function connect() {
  const source = new EventSource("/api/rig/events");
  source.addEventListener("open", () => { $("link").textContent = "live"; });
  source.addEventListener("history", (m) => showHistory(JSON.parse(m.data)));
  source.addEventListener("status", (m) => showStatus(JSON.parse(m.data)));
  source.addEventListener("rig", (m) => onEvent(JSON.parse(m.data)));
  source.addEventListener("error", () => { $("link").textContent = "reconnecting…"; });
}

// The patient the next START is for: a worklist row (one click) or typed fields.
let picked = null;
function patientArgs() {
  if (picked) return picked;
  const typed = { patient_id: $("patient-id").value.trim(), patient_name: $("patient-name").value.trim(), birth_date: $("birth-date").value.trim() };
  return typed.patient_id || typed.patient_name ? typed : {};
}
function showChosen() {
  const p = patientArgs();
  $("chosen").textContent = p.patient_id || p.patient_name
    ? `START scans for ${personName(p.patient_name)} (${p.patient_id || "no id"})${p.accession_number ? `, order ${p.accession_number}` : ""}`
    : "No patient chosen: START scans for nobody.";
}
["patient-id", "patient-name", "birth-date"].forEach((id) => $(id).addEventListener("input", () => {
  picked = null;
  document.querySelectorAll("#worklist tr").forEach((r) => r.classList.remove("picked"));
  showChosen();
}));

async function loadWorklist() {
  $("worklist-note").textContent = "Asking the worklist…";
  const rows = document.querySelector("#worklist tbody");
  try {
    const { items, problems } = await getJSON("/api/rig/worklist");
    rows.replaceChildren(...items.map((item) => {
      const row = el("tr", { class: "pick" }, el("td", {}, el("b", {}, personName(item.patient_name))), el("td", {}, item.patient_id),
        el("td", {}, item.birth_date || "–"), el("td", {}, item.procedure || ""), el("td", {}, item.scheduled || ""));
      row.addEventListener("click", () => {
        picked = item;
        rows.querySelectorAll("tr").forEach((r) => r.classList.toggle("picked", r === row));
        showChosen();
      });
      return row;
    }));
    $("worklist-note").replaceChildren(items.length ? "Today's worklist: click the patient, then START." : "Nothing scheduled today.",
      ...problems.map((p) => el("div", { class: "error" }, p)));
  } catch (error) { $("worklist-note").textContent = String(error.message || error); }
  hooks.worklistLoaded = true;
}
$("worklist-refresh").addEventListener("click", loadWorklist);

async function act(action) {
  $("action-error").textContent = "";
  const body = action === "scan" ? { ...patientArgs() } : {};
  for (const key of ["procedure", "scheduled"]) delete body[key];
  try { await send("POST", `/api/rig/${action}`, body); } catch (error) { $("action-error").textContent = String(error.message || error); }
}
$("start").addEventListener("click", () => act("scan"));
$("abort").addEventListener("click", () => act("abort"));
$("reset").addEventListener("click", () => act("reset"));
showState("–");
getJSON("/api/config").then((config) => {
  if (config.poses) { poses = config.poses; document.querySelectorAll(".n-poses").forEach((n) => { n.textContent = poses; }); }
  if (!config.rig) $("link").textContent = "no rig daemon (viewer only)";
  else connect();
  if (config.worklist) { $("worklist-refresh").hidden = false; loadWorklist(); }
});
